MODULE IrTrack
    !***********************************************************************
    ! irtrack robot link, protocol version 1 (docs/robot-protocol.md).
    ! The controller is the TCP server; irtrackd connects as the client and
    ! streams targets. Step-by-step: one target, one MoveL, one credit line.
    ! Needs RobotWare option 616-1 PC Interface (socket messaging).
    !***********************************************************************

    ! ---- Installation settings (edit these) ------------------------------
    ! Controller address the server binds to: the service port on IRC5 is
    ! 192.168.125.1, the virtual controller in RobotStudio uses 127.0.0.1.
    PERS string irtIp := "192.168.125.1";
    PERS num irtPort := 1025;
    CONST string irtName := "IRC5";
    ! Motion data: speed, zone (fine = stop at every target), tool, work
    ! object. Coordinates received are in irtWobj (use wobj0 = base frame).
    PERS speeddata irtSpeed := [100, 50, 5000, 1000];
    PERS zonedata irtZone := [TRUE, 0.3, 0.3, 0.3, 0.03, 0.3, 0.03];
    PERS tooldata irtTool := [TRUE, [[0, 0, 100], [1, 0, 0, 0]], [1, [0, 0, 1], [1, 0, 0, 0], 0, 0, 0]];
    PERS wobjdata irtWobj := [FALSE, TRUE, "", [[0, 0, 0], [1, 0, 0, 0]], [[0, 0, 0], [1, 0, 0, 0]]];
    ! Second line of defence besides irtrackd's own workspace check (mm).
    PERS pos irtBoxMin := [200, -400, 0];
    PERS pos irtBoxMax := [800, 400, 600];
    ! Receive poll period (s) and how long the tracker may stay silent (s).
    ! irtPeerTimeout must exceed irtrackd's heartbeat_ms; irtrackd's
    ! peer_timeout_ms must exceed the longest single move (max_step / speed).
    PERS num irtRecvPoll := 0.2;
    PERS num irtPeerTimeout := 1;
    ! Survey mode (host-tools survey, docs/teach-in.md): every target is a
    ! fine point at the slow survey speed, moved and reported with the
    ! survey tool (tool0: the flange; the LED offset is solved by the PC).
    PERS bool irtSurvey := FALSE;
    PERS speeddata irtSurveySpeed := [50, 20, 5000, 1000];
    PERS tooldata irtSurveyTool := [TRUE, [[0, 0, 0], [1, 0, 0, 0]], [1, [0, 0, 1], [1, 0, 0, 0], 0, 0, 0]];

    ! ---- Protocol constants (checked against the Rust codec by a test) ----
    CONST num IRT_VERSION := 1;
    CONST num IRT_MAX_LINE := 80;
    CONST num IRT_SEQ_COL := 3;
    CONST num IRT_SEQ_LEN := 6;
    CONST num IRT_COORD_LEN := 8;
    CONST num IRT_QUAT_LEN := 9;
    CONST num IRT_T_X_COL := 10;
    CONST num IRT_T_Y_COL := 19;
    CONST num IRT_T_Z_COL := 28;
    CONST num IRT_Q_Q1_COL := 37;
    CONST num IRT_HOLD_CODE_COL := 6;
    CONST num IRT_POSE_COL := 6;
    CONST num IRT_WINDOW := 1;
    CONST num IRT_REJ_UNREACHABLE := 1;
    CONST num IRT_REJ_MALFORMED := 99;

    ! ---- State ------------------------------------------------------------
    VAR socketdev irtServer;
    VAR socketdev irtClient;
    VAR string irtRx := "";
    VAR bool irtConnected := FALSE;
    VAR num irtAckSeq := 0;
    VAR num irtLastRxSeq := 0;
    VAR num irtBeat := 0;
    VAR num irtSilent := 0;
    VAR bool irtTargetOk := FALSE;

    PROC main()
        ConfL\Off;
        SingArea\Wrist;
        WHILE TRUE DO
            IrtServeOnce;
        ENDWHILE
    ENDPROC

    ! Accepts one tracker connection and serves it until it ends.
    PROC IrtServeOnce()
        VAR string line;
        SocketClose irtClient;
        SocketClose irtServer;
        SocketCreate irtServer;
        SocketBind irtServer, irtIp, irtPort;
        SocketListen irtServer;
        TPWrite "IrTrack: waiting for irtrackd on port " \Num:=irtPort;
        SocketAccept irtServer, irtClient \Time:=WAIT_MAX;
        ! Every connection starts from zero.
        irtRx := "";
        irtAckSeq := 0;
        irtLastRxSeq := 0;
        irtSilent := 0;
        irtConnected := TRUE;
        IrtSend "HELLO 01 ROBOT " + irtName;
        IrtSendCredit;
        WHILE irtConnected DO
            line := IrtReadLine();
            IF line = "" THEN
                ! Poll period passed without a complete line.
                irtSilent := irtSilent + 1;
                IF irtSilent * irtRecvPoll > irtPeerTimeout THEN
                    TPWrite "IrTrack: tracker silent, closing";
                    irtConnected := FALSE;
                ELSE
                    IrtSendBeat;
                ENDIF
            ELSE
                irtSilent := 0;
                IrtDispatch line;
            ENDIF
        ENDWHILE
        SocketClose irtClient;
        SocketClose irtServer;
    ERROR
        IF ERRNO = ERR_SOCK_CLOSED THEN
            TPWrite "IrTrack: connection closed";
            StopMove;
            ClearPath;
            StartMove;
            SocketClose irtClient;
            SocketClose irtServer;
            RETURN;
        ELSEIF ERRNO = ERR_SOCK_TIMEOUT THEN
            SocketClose irtClient;
            SocketClose irtServer;
            RETURN;
        ENDIF
    ENDPROC

    ! Returns one line without its newline, or "" when the poll period
    ! passed first. A partial line stays in irtRx for the next call.
    FUNC string IrtReadLine()
        VAR string ch;
        VAR string done;
        WHILE TRUE DO
            SocketReceive irtClient \Str:=ch \ReadNoOfBytes:=1 \Time:=irtRecvPoll;
            IF ch = "\0A" THEN
                done := irtRx;
                irtRx := "";
                RETURN done;
            ENDIF
            IF StrLen(irtRx) >= IRT_MAX_LINE - 1 THEN
                ! Longer than the protocol allows: drop it.
                irtRx := "";
                IrtReject 0, IRT_REJ_MALFORMED, "MALFORMED";
            ELSE
                irtRx := irtRx + ch;
            ENDIF
        ENDWHILE
    ERROR
        IF ERRNO = ERR_SOCK_TIMEOUT THEN
            RETURN "";
        ENDIF
        ! ERR_SOCK_CLOSED and the rest go to IrtServeOnce.
        RAISE;
    ENDFUNC

    PROC IrtDispatch(string line)
        VAR num n;
        n := StrLen(line);
        IF n = 35 AND StrPart(line, 1, 2) = "T " THEN
            IrtTarget line, FALSE;
        ELSEIF n = 75 AND StrPart(line, 1, 2) = "Q " THEN
            IrtTarget line, TRUE;
        ELSEIF n >= 8 AND StrPart(line, 1, 5) = "HOLD " THEN
            IrtHold line;
        ELSEIF n = 11 AND StrPart(line, 1, 5) = "POSE " THEN
            IrtSendPose StrPart(line, IRT_POSE_COL, IRT_SEQ_LEN);
        ELSEIF n = 11 AND StrPart(line, 1, 5) = "BEAT " THEN
            ! Heartbeat: receiving it already reset the silence counter.
        ELSEIF n >= 17 AND StrPart(line, 1, 6) = "HELLO " THEN
            IF StrPart(line, 7, 2) <> "01" THEN
                TPWrite "IrTrack: tracker speaks another protocol version: " + line;
                irtConnected := FALSE;
            ENDIF
        ELSEIF line = "BYE" THEN
            irtConnected := FALSE;
        ELSE
            IrtReject 0, IRT_REJ_MALFORMED, "MALFORMED";
        ENDIF
    ENDPROC

    ! Signed fixed-point field "+dddd.dd" / "+d.dddddd" to num.
    FUNC num IrtField(string f, INOUT bool ok)
        VAR num v;
        VAR string sign;
        sign := StrPart(f, 1, 1);
        IF NOT StrToVal(StrPart(f, 2, StrLen(f) - 1), v) THEN
            ok := FALSE;
            RETURN 0;
        ENDIF
        IF sign = "-" THEN
            RETURN -v;
        ELSEIF sign = "+" THEN
            RETURN v;
        ENDIF
        ok := FALSE;
        RETURN 0;
    ENDFUNC

    PROC IrtTarget(string line, bool withRot)
        VAR bool ok := TRUE;
        VAR num seq;
        VAR robtarget p;
        VAR jointtarget jt;
        VAR orient q;
        IF NOT StrToVal(StrPart(line, IRT_SEQ_COL, IRT_SEQ_LEN), seq) THEN
            IrtReject 0, IRT_REJ_MALFORMED, "MALFORMED";
            RETURN;
        ENDIF
        irtLastRxSeq := seq;
        IF irtSurvey THEN
            p := CRobT(\Tool:=irtSurveyTool \WObj:=irtWobj);
        ELSE
            p := CRobT(\Tool:=irtTool \WObj:=irtWobj);
        ENDIF
        p.trans.x := IrtField(StrPart(line, IRT_T_X_COL, IRT_COORD_LEN), ok);
        p.trans.y := IrtField(StrPart(line, IRT_T_Y_COL, IRT_COORD_LEN), ok);
        p.trans.z := IrtField(StrPart(line, IRT_T_Z_COL, IRT_COORD_LEN), ok);
        IF withRot THEN
            q.q1 := IrtField(StrPart(line, IRT_Q_Q1_COL, IRT_QUAT_LEN), ok);
            q.q2 := IrtField(StrPart(line, IRT_Q_Q1_COL + 10, IRT_QUAT_LEN), ok);
            q.q3 := IrtField(StrPart(line, IRT_Q_Q1_COL + 20, IRT_QUAT_LEN), ok);
            q.q4 := IrtField(StrPart(line, IRT_Q_Q1_COL + 30, IRT_QUAT_LEN), ok);
            p.rot := NOrient(q);
        ENDIF
        IF NOT ok THEN
            IrtReject seq, IRT_REJ_MALFORMED, "MALFORMED";
            RETURN;
        ENDIF
        IF p.trans.x < irtBoxMin.x OR p.trans.x > irtBoxMax.x OR p.trans.y < irtBoxMin.y OR p.trans.y > irtBoxMax.y OR p.trans.z < irtBoxMin.z OR p.trans.z > irtBoxMax.z THEN
            IrtReject seq, IRT_REJ_UNREACHABLE, "OUTSIDE_BOX";
            RETURN;
        ENDIF
        ! CalcJointT raises ERR_ROBLIMIT for a target out of reach.
        irtTargetOk := TRUE;
        IF irtSurvey THEN
            jt := CalcJointT(p, irtSurveyTool \WObj:=irtWobj);
        ELSE
            jt := CalcJointT(p, irtTool \WObj:=irtWobj);
        ENDIF
        IF NOT irtTargetOk THEN
            IrtReject seq, IRT_REJ_UNREACHABLE, "UNREACHABLE";
            RETURN;
        ENDIF
        IF irtSurvey THEN
            ! Survey: stop exactly at every point (fine), slowly.
            MoveL p, irtSurveySpeed, fine, irtSurveyTool \WObj:=irtWobj;
        ELSE
            MoveL p, irtSpeed, irtZone, irtTool \WObj:=irtWobj;
        ENDIF
        irtAckSeq := seq;
        IrtSendCredit;
    ERROR
        IF ERRNO = ERR_ROBLIMIT THEN
            irtTargetOk := FALSE;
            TRYNEXT;
        ENDIF
    ENDPROC

    PROC IrtHold(string line)
        TPWrite "IrTrack: HOLD " + StrPart(line, IRT_HOLD_CODE_COL, StrLen(line) - IRT_HOLD_CODE_COL + 1);
        StopMove;
        ClearPath;
        StartMove;
        ! Everything received so far counts as consumed.
        irtAckSeq := irtLastRxSeq;
        IrtSendCredit;
    ENDPROC

    PROC IrtSend(string text)
        SocketSend irtClient \Str:=text + "\0A";
    ENDPROC

    PROC IrtSendCredit()
        VAR robtarget now;
        now := CRobT(\Tool:=irtTool \WObj:=irtWobj);
        IrtSend "C " + IrtDigits(irtAckSeq, 6) + " " + IrtDigits(IRT_WINDOW, 2) + " " + IrtCoord(now.trans.x) + " " + IrtCoord(now.trans.y) + " " + IrtCoord(now.trans.z);
    ENDPROC

    ! Answer to "POSE nnnnnn": the TCP pose now (CRobT), "A nnnnnn x y z
    ! q1 q2 q3 q4" in the Q layout. Targets are fine points in survey mode,
    ! so the robot stands still when it reads this line.
    PROC IrtSendPose(string counter)
        VAR robtarget now;
        VAR num c;
        IF NOT StrToVal(counter, c) THEN
            IrtReject 0, IRT_REJ_MALFORMED, "MALFORMED";
            RETURN;
        ENDIF
        IF irtSurvey THEN
            now := CRobT(\Tool:=irtSurveyTool \WObj:=irtWobj);
        ELSE
            now := CRobT(\Tool:=irtTool \WObj:=irtWobj);
        ENDIF
        IrtSend "A " + IrtDigits(c, 6) + " " + IrtCoord(now.trans.x) + " " + IrtCoord(now.trans.y) + " " + IrtCoord(now.trans.z) + " " + IrtQuat(now.rot.q1) + " " + IrtQuat(now.rot.q2) + " " + IrtQuat(now.rot.q3) + " " + IrtQuat(now.rot.q4);
    ENDPROC

    PROC IrtSendBeat()
        irtBeat := (irtBeat + 1) MOD 1000000;
        IrtSend "BEAT " + IrtDigits(irtBeat, 6);
    ENDPROC

    PROC IrtReject(num seq, num code, string reason)
        IrtSend "X " + IrtDigits(seq, 6) + " " + IrtDigits(code, 2) + " " + reason;
        ! A rejected target is consumed: grant the credit back.
        IF seq > 0 THEN
            irtAckSeq := seq;
            IrtSendCredit;
        ENDIF
    ENDPROC

    ! Non-negative integer, zero padded to width digits.
    FUNC string IrtDigits(num v, num width)
        VAR string s;
        s := NumToStr(Round(v), 0);
        WHILE StrLen(s) < width DO
            s := "0" + s;
        ENDWHILE
        RETURN s;
    ENDFUNC

    ! "+dddd.dd", clamped to +-9999.99.
    FUNC string IrtCoord(num v)
        VAR string sign := "+";
        VAR num cents;
        IF v < 0 THEN
            sign := "-";
        ENDIF
        cents := Round(Abs(v) * 100);
        IF cents > 999999 THEN
            cents := 999999;
        ENDIF
        RETURN sign + IrtDigits(cents DIV 100, 4) + "." + IrtDigits(cents MOD 100, 2);
    ENDFUNC

    ! Quaternion component "+d.dddddd", clamped to +-1.
    FUNC string IrtQuat(num v)
        VAR string sign := "+";
        VAR num u;
        IF v < 0 THEN
            sign := "-";
        ENDIF
        u := Round(Abs(v) * 1000000);
        IF u > 1000000 THEN
            u := 1000000;
        ENDIF
        RETURN sign + IrtDigits(u DIV 1000000, 1) + "." + IrtDigits(u MOD 1000000, 6);
    ENDFUNC
ENDMODULE
