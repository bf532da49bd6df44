//! `host-tools cluster-keys --boards b0,b1 --out DIR`: the credentials of a cluster's Zenoh
//! transport (docs/cluster.md, "Credentials"). One random password per camera board
//! (`DIR/<board>.password`, for that board's `[cluster] password_file`) and the solver's
//! dictionary of all of them (`DIR/solver.credentials`, its `credentials_file`), every file
//! mode 0600; the passwords come from the operating system's CSPRNG
//! (`irtrack_cluster::credentials`, the same code irtrackd reads them with).
//!
//! The files are copied to the boards by hand (scp), not pushed through the parameter port:
//! that port carries signed but unencrypted blobs, so a password sent through it could be
//! read by anyone on the cell's network.

use std::path::PathBuf;

use anyhow::Result;
use irtrack_cluster::credentials::{dictionary_path, password_path, write_new_credentials};

/// Arguments.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The camera boards' names (their `[cluster] board`), comma separated.
    #[arg(long, value_delimiter = ',', required = true)]
    pub boards: Vec<String>,
    /// Directory to write `<board>.password` and `solver.credentials` into (created).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Replace existing files (the old passwords stop working once the solver has the new
    /// dictionary).
    #[arg(long)]
    pub force: bool,
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    let boards: Vec<&str> = args.boards.iter().map(|b| b.trim()).collect();
    let written = write_new_credentials(&args.out, &boards, args.force)?;
    for c in &written {
        println!(
            "board {}: {} (mode 600) -> its [cluster] password_file",
            c.board,
            password_path(&args.out, &c.board).display()
        );
    }
    println!(
        "solver: {} (mode 600) -> its [cluster] credentials_file",
        dictionary_path(&args.out).display()
    );
    println!(
        "copy each file to its board by hand (scp, then chmod 600; docs/cluster.md \"Credentials\"): they are secrets and the parameter port does not encrypt"
    );
    Ok(())
}
