//! irtrackd: the irtrack board service (see docs/irtrackd.md).

use std::io::{IsTerminal, Write};
use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;

use irtrack_firmware::app::{self, Overrides};
use irtrack_firmware::config::{self, Config, SourceKind};
use irtrack_firmware::watchdog;

#[derive(Debug, Parser)]
#[command(
    name = "irtrackd",
    version,
    about = "irtrack board service: capture, tracking, position stream"
)]
struct Cli {
    /// Config file (TOML). Without it, built-in defaults (simulated source) are used unless
    /// the default file exists.
    #[arg(short, long)]
    config: Option<PathBuf>,
    /// Validate the configuration and exit.
    #[arg(long)]
    check_config: bool,
    /// Override `source.kind`.
    #[arg(long, value_enum)]
    source: Option<SourceKind>,
    /// Replay directory (implies `--source replay`).
    #[arg(long)]
    replay_dir: Option<PathBuf>,
    /// Replay on the shared clock: the recording's origin plays at this CLOCK_REALTIME
    /// instant, seconds since 1970 (`[source.replay] start_at_unix_s`; give every camera
    /// board of a multi-board recording the same, e.g. `$(( $(date +%s) + 10 ))`).
    #[arg(long, value_name = "UNIX_S")]
    replay_start_at: Option<f64>,
    /// Override `service.state_dir`.
    #[arg(long)]
    state_dir: Option<PathBuf>,
    /// Bind every endpoint on this IP with OS-chosen ports (tests, several instances).
    #[arg(long)]
    ephemeral_ports: Option<std::net::IpAddr>,
    #[arg(long)]
    listen_params: Option<String>,
    #[arg(long)]
    listen_stream: Option<String>,
    #[arg(long)]
    listen_binary: Option<String>,
    #[arg(long)]
    listen_status: Option<String>,
    /// Override the simulated source's frame rate.
    #[arg(long)]
    sim_fps: Option<f64>,
    /// Simulated source: use the simulator's rig when no parameters are stored.
    #[arg(long)]
    params_from_simulator: bool,
    /// Read an operator password from standard input, print its Argon2id hash for
    /// `[service] operator_password_hash`, and exit.
    #[arg(long)]
    hash_password: bool,
    /// Write linuxptp's `ptp4l.conf` (and the `hardware-timestamps` marker for phc2sys) from
    /// `[clock]` into DIR and exit: 0 when `[clock] ptp = true`, 1 when it is off (the image's
    /// `irtrack-ptp4l.service` runs this as its `ExecCondition`, so PTP stays off then).
    #[arg(long, value_name = "DIR")]
    write_ptp_config: Option<PathBuf>,
}

fn apply_overrides(cfg: &mut Config, cli: &Cli) -> anyhow::Result<()> {
    if let Some(k) = cli.source {
        cfg.source.kind = k;
    }
    if let Some(dir) = &cli.replay_dir {
        cfg.source.kind = SourceKind::Replay;
        let r = cfg
            .source
            .replay
            .get_or_insert_with(|| irtrack_firmware::source::replay::ReplayConfig {
                dir: dir.clone(),
                ..Default::default()
            });
        r.dir = dir.clone();
    }
    if let Some(at) = cli.replay_start_at {
        match cfg.source.replay.as_mut() {
            Some(r) => r.start_at_unix_s = Some(at),
            None => {
                anyhow::bail!("--replay-start-at needs a replay source ([source.replay] or --replay-dir)")
            }
        }
    }
    if let Some(d) = &cli.state_dir {
        cfg.service.state_dir = d.clone();
    }
    if let Some(ip) = cli.ephemeral_ports {
        let a = std::net::SocketAddr::new(ip, 0).to_string();
        cfg.listen.params = a.clone();
        cfg.listen.stream_ndjson = a.clone();
        cfg.listen.stream_binary = a.clone();
        cfg.listen.status = a;
        // NatNet's command and (multicast) data ports too: its defaults are fixed ports.
        cfg.outputs.natnet.use_ephemeral_ports(ip)?;
    }
    for (v, slot) in [
        (&cli.listen_params, &mut cfg.listen.params),
        (&cli.listen_stream, &mut cfg.listen.stream_ndjson),
        (&cli.listen_binary, &mut cfg.listen.stream_binary),
        (&cli.listen_status, &mut cfg.listen.status),
    ] {
        if let Some(v) = v {
            *slot = v.clone();
        }
    }
    if let Some(fps) = cli.sim_fps {
        cfg.source.sim.get_or_insert_with(Default::default).fps = fps;
    }
    if cli.params_from_simulator {
        cfg.service.params_from_simulator = true;
    }
    Ok(())
}

fn load_config(cli: &Cli) -> anyhow::Result<Config> {
    let path = cli.config.clone().or_else(|| {
        let p = PathBuf::from(config::DEFAULT_CONFIG_PATH);
        p.exists().then_some(p)
    });
    let mut cfg = match &path {
        Some(p) => Config::load(p)?,
        None => Config::default(),
    };
    apply_overrides(&mut cfg, cli)?;
    cfg.validate().context("after command-line overrides")?;
    Ok(cfg)
}

fn init_logging() {
    use tracing_subscriber::prelude::*;
    use tracing_subscriber::{EnvFilter, Layer, fmt};
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    // journald stamps lines itself and shows escape codes literally.
    let journald = std::env::var_os("JOURNAL_STREAM").is_some();
    let log = fmt::layer()
        .with_writer(std::io::stderr)
        .with_ansi(!journald && std::io::stderr().is_terminal());
    let log = if journald {
        log.without_time().boxed()
    } else {
        log.boxed()
    };
    // The log's filter is the log's own (a layer filter), so the cluster's refusal counter
    // gets Zenoh's accept events whatever RUST_LOG says (docs/cluster.md, "Refused peers").
    let subscriber = tracing_subscriber::registry().with(log.with_filter(filter));
    #[cfg(feature = "cluster")]
    let subscriber = subscriber.with(irtrack_cluster::refusals::refusal_layer());
    subscriber.init();
}

/// `--hash-password`: one line from stdin (trailing newline removed) → PHC string on stdout.
fn hash_password() -> anyhow::Result<()> {
    let mut line = String::new();
    std::io::stdin()
        .read_line(&mut line)
        .context("reading the password from standard input")?;
    let password = line.trim_end_matches(['\n', '\r']);
    let phc = irtrack_firmware::net::auth::hash_password(password)?;
    println!("{phc}");
    eprintln!("irtrackd: put this line into the config as\n[service]\noperator_password_hash = \"{phc}\"");
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    if cli.hash_password {
        return hash_password();
    }
    init_logging();
    let mut cfg = match load_config(&cli) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("irtrackd: {e:#}");
            std::process::exit(2);
        }
    };
    // Credentials pushed earlier count for `--check-config` as they do at start.
    cfg.cluster.adopt_pushed_credentials(&cfg.service.state_dir);
    if let Some(dir) = &cli.write_ptp_config {
        if !cfg.clock.ptp {
            println!("irtrackd: [clock] ptp is off: no PTP config written");
            std::process::exit(1);
        }
        cfg.clock.write_files(dir)?;
        println!(
            "irtrackd: wrote {} ({:?} time stamping on {}, role {:?}, domain {})",
            dir.join("ptp4l.conf").display(),
            cfg.clock.time_stamping,
            cfg.clock.interface,
            cfg.clock.role,
            cfg.clock.domain
        );
        return Ok(());
    }
    if cli.check_config {
        let keys = cfg.params.load_keys()?;
        use irtrack_firmware::cluster::Role;
        // A solver's positions come from its camera boards; `[source]` is then only its own
        // cameras (when `own_cameras`), so say which.
        let source = match (cfg.cluster.role, cfg.cluster.own_cameras) {
            (Role::Solver, false) => "the camera boards' observations (cluster solver)".to_string(),
            (Role::Solver, true) => format!(
                "the camera boards' observations and its own cameras ({:?})",
                cfg.source.kind
            ),
            _ => format!("{:?}", cfg.source.kind),
        };
        println!(
            "irtrackd: config OK (source {source}, state dir {}, params {}, stream {}, binary {}, status {})",
            cfg.service.state_dir.display(),
            cfg.listen.params,
            cfg.listen.stream_ndjson,
            cfg.listen.stream_binary,
            cfg.listen.status
        );
        let feature = if cfg!(feature = "cluster") {
            "built with the cluster feature"
        } else {
            "built without the cluster feature (standalone only)"
        };
        match cfg.cluster.role {
            Role::Standalone => {
                println!("irtrackd: cluster role standalone (one board); this binary is {feature}")
            }
            role => println!(
                "irtrackd: cluster role {} (board {:?}, rig {:?}, listen {:?}, connect {:?}{}); this binary is {feature}",
                match role {
                    Role::Camera => "camera",
                    _ => "solver",
                },
                cfg.cluster.board,
                cfg.cluster.rig,
                cfg.cluster.listen,
                cfg.cluster.connect,
                if role == Role::Solver {
                    format!(
                        ", {} cameras in all, pairing by {}",
                        cfg.cluster.image_sizes_px.len(),
                        if cfg.cluster.trigger {
                            "the trigger counter"
                        } else {
                            "timestamps"
                        }
                    )
                } else {
                    String::new()
                }
            ),
        }
        println!(
            "irtrackd: parameter pushes: {} trusted key(s){}",
            keys.len(),
            if cfg.params.allow_unsigned {
                ", unsigned blobs accepted (development mode)"
            } else {
                ""
            }
        );
        println!(
            "irtrackd: operator sign-in: {}",
            if cfg.service.operator_password_hash.is_some() {
                "password configured (changes on the status port need a sign-in)"
            } else {
                "no password configured: every change request on the status port is refused"
            }
        );
        if let Some(line) = cfg.cluster.auth_summary() {
            println!("irtrackd: {line}");
        }
        let tuning_path = cfg.service.state_dir.join(irtrack_firmware::tuning::TUNING_FILE);
        match irtrack_firmware::tuning::TuningFile::load(&cfg.service.state_dir)? {
            Some(t) => {
                let applied = t
                    .apply_to(&cfg.tracking)
                    .map_err(|e| anyhow::anyhow!("{}: {e}", tuning_path.display()))?;
                println!(
                    "irtrackd: saved tuning {} overrides the config at start: threshold {} DN, blob area {}..={} px, {} camera setting(s)",
                    tuning_path.display(),
                    applied.threshold_dn,
                    applied.min_area_px,
                    applied.max_area_px,
                    t.camera.len()
                );
            }
            None => println!(
                "irtrackd: no saved tuning ({} absent); [tracking] from the config applies",
                tuning_path.display()
            ),
        }
        return Ok(());
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("irtrackd-io")
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    rt.block_on(run(cfg))
}

async fn run(cfg: Config) -> anyhow::Result<()> {
    let mut running = app::start(cfg, Overrides::default()).await?;
    let line = running.addrs.ready_line();
    {
        let mut out = std::io::stdout().lock();
        writeln!(out, "{line}")?;
        out.flush()?;
    }
    tracing::info!("{line}");
    watchdog::notify_ready(&line);
    let _watchdog = watchdog::spawn(running.status.clone());
    let mut loop_done = running.take_loop_result();

    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
    let exit = loop {
        tokio::select! {
            _ = tokio::signal::ctrl_c() => break Ok(()),
            _ = sigterm.recv() => break Ok(()),
            r = wait_loop(&mut loop_done) => match r {
                // Source ended on purpose (replay): keep serving status until stopped.
                Ok(Ok(())) => {
                    tracing::info!("processing loop finished; services stay up until stopped");
                    loop_done = None;
                }
                Ok(Err(e)) => break Err(anyhow::Error::new(e).context("processing loop failed")),
                Err(_) => break Err(anyhow::anyhow!("processing loop thread died")),
            },
        }
    };
    tracing::info!("stopping");
    watchdog::notify_stopping();
    running.shutdown().await;
    exit
}

async fn wait_loop(
    rx: &mut Option<tokio::sync::oneshot::Receiver<irtrack_firmware::Result<()>>>,
) -> Result<irtrack_firmware::Result<()>, tokio::sync::oneshot::error::RecvError> {
    match rx {
        Some(r) => r.await,
        None => std::future::pending().await,
    }
}
