MODULE IrTrackEgm
    !***********************************************************************
    ! irtrack over ABB Externally Guided Motion (EGM), position guidance.
    ! irtrackd is the EGM sensor ([robot] kind = "egm", docs/robot-streaming.md):
    ! the controller sends EgmRobot over UDP every cycle (4 ms) and irtrackd
    ! answers each with an EgmSensor carrying the pose to go to. irtrackd
    ! holds the robot (answers with the robot's own pose) until the operator
    ! enables motion, and on every safety condition.
    ! Needs RobotWare option 689-1 Externally Guided Motion, and a UDPUC
    ! transmission protocol "IrTrackUC" pointing at the board (rapid/README.md).
    !***********************************************************************

    ! ---- Installation settings (edit these) ------------------------------
    ! Transmission protocol name (Configuration > Communication > Transmission
    ! Protocol, type UDPUC, remote address = the board, remote port = the port
    ! of irtrackd's [robot] address) and the motion data set used.
    PERS string egmUcDevice := "IrTrackUC";
    PERS string egmExtConfig := "default";
    ! Tool whose TCP follows the marker; work object the poses are given in
    ! (keep wobj0 when irtrackd's registration maps to the base frame).
    PERS tooldata egmTool := [TRUE, [[0, 0, 100], [1, 0, 0, 0]], [1, [0, 0, 1], [1, 0, 0, 0], 0, 0, 0]];
    PERS wobjdata egmWobj := [FALSE, TRUE, "", [[0, 0, 0], [1, 0, 0, 0]], [[0, 0, 0], [1, 0, 0, 0]]];
    ! Convergence band: EGMRunPose counts as converged inside these (mm, deg).
    CONST egm_minmax egmLin := [-1, 1];
    CONST egm_minmax egmRot := [-2, 2];
    ! Controller-side limits, a second line of defence besides irtrackd's
    ! supervisor: largest deviation of the commanded path (mm) and speed
    ! deviation (mm/s) EGM may apply. Keep egmMaxSpeedDev at or below
    ! irtrackd's robot.safety.max_speed_mm_s.
    PERS num egmMaxPosDev := 1000;
    PERS num egmMaxSpeedDev := 250;
    ! Low-pass filter of the controller on the sensor's poses (Hz), the
    ! expected sensor period (ms, = the controller cycle) and how long
    ! without a sensor message ends the session (s).
    PERS num egmLpFilter := 20;
    PERS num egmSampleRate := 4;
    PERS num egmCommTimeout := 1;
    ! How long one EGMRunPose lasts before it is restarted (s); the pose
    ! stream continues across restarts.
    PERS num egmCondTime := 60;

    ! ---- Constants (checked against the Rust side by a test) ---------------
    ! EGM cycle of irtrackd's documentation and simulated controller (ms).
    CONST num EGM_CYCLE_MS := 4;

    ! ---- State ------------------------------------------------------------
    VAR egmident egmId;
    VAR egmstate egmState;
    CONST pose egmNoOffset := [[0, 0, 0], [1, 0, 0, 0]];

    PROC main()
        ConfL\Off;
        SingArea\Wrist;
        WHILE TRUE DO
            EgmFollowOnce;
        ENDWHILE
    ENDPROC

    ! Sets up EGM (once per program start) and follows irtrackd until the
    ! condition time ends or communication stops.
    PROC EgmFollowOnce()
        EGMGetId egmId;
        egmState := EGMGetState(egmId);
        IF egmState <= EGM_STATE_CONNECTED THEN
            EGMSetupUC ROB_1, egmId, egmExtConfig, egmUcDevice \Pose \CommTimeout:=egmCommTimeout;
        ENDIF
        TPWrite "IrTrackEgm: following irtrackd (enable motion on the tracker)";
        EGMActPose egmId \Tool:=egmTool \WObj:=egmWobj, egmNoOffset, EGM_FRAME_WOBJ, egmNoOffset, EGM_FRAME_WOBJ \x:=egmLin \y:=egmLin \z:=egmLin \rx:=egmRot \ry:=egmRot \rz:=egmRot \LpFilter:=egmLpFilter \SampleRate:=egmSampleRate \MaxPosDeviation:=egmMaxPosDev \MaxSpeedDeviation:=egmMaxSpeedDev;
        EGMRunPose egmId, EGM_STOP_HOLD \x \y \z \Rx \Ry \Rz \CondTime:=egmCondTime \RampInTime:=0.05 \PosCorrGain:=1;
    ERROR
        IF ERRNO = ERR_UDPUC_COMM THEN
            ! irtrackd stopped answering: EGM has stopped the motion already.
            TPWrite "IrTrackEgm: no answer from irtrackd, restarting";
            EGMReset egmId;
            WaitTime 1;
            RETURN;
        ENDIF
    ENDPROC

ENDMODULE
