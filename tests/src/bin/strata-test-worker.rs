//! The worker, as a binary of this package, so that end-to-end tests here can spawn
//! workers through `Cluster::start` (`ClusterOptions::worker_exe`); cargo only tells a
//! package's tests where that package's own binaries are. It is the `worker` binary's
//! `--connect` mode, nothing else.

use clap::Parser;
use std::process::ExitCode;

/// A Strata worker for the end-to-end tests (same flags as `worker --connect`).
#[derive(Parser)]
#[command(name = "strata-test-worker", about)]
struct Cli {
    #[command(flatten)]
    join: strata_worker::cli::JoinArgs,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match strata_worker::cli::join(cli.join) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
