//! `worker`: the process the coordinator launches to render its share of a scene.
//!
//! `worker --connect HOST:PORT --fingerprint-file F --secret-file S` joins a render run:
//! the coordinator spawns workers this way on one machine, and a launcher (`srun`, `ssh`)
//! does on a cluster (see `configs/slurm-render.sh`).
//!
//! The render engine is the library (`strata_worker`). A worker reads pages of any store
//! concurrently through positional reads, on the page cache's loader threads
//! (`render.loader_threads`). `worker read-bench` measures the loader threads' read path
//! on its own: random page reads (read, checksum, decode) from N threads, without the
//! cache or the render.

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use std::os::fd::AsRawFd;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;
use strata_common::digest::fmix64;
use strata_common::store::PageStore;

/// Strata worker process.
#[derive(Parser)]
#[command(name = "worker", version, about)]
#[command(args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    join: strata_worker::cli::JoinArgs,
}

#[derive(Subcommand)]
enum Command {
    /// Random page reads (read, checksum, decode) from several threads; prints pages/s and MB/s.
    ReadBench {
        /// Page store.
        store: PathBuf,
        /// Reader threads.
        #[arg(long, default_value_t = 1)]
        threads: usize,
        /// Pages to read in total.
        #[arg(long, default_value_t = 2000)]
        pages: u64,
        /// Drop the store's pages from the OS file cache first (posix_fadvise DONTNEED), so reads hit the disk.
        #[arg(long)]
        cold: bool,
        /// Seed of the random page sequence.
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
}

fn read_bench(store: PathBuf, threads: usize, pages: u64, cold: bool, seed: u64) -> Result<()> {
    let s = PageStore::open(&store).with_context(|| format!("cannot open {}", store.display()))?;
    let candidates: Vec<_> = s
        .index()
        .iter()
        .filter(|e| e.has_payload())
        .map(|e| e.id)
        .collect();
    anyhow::ensure!(
        !candidates.is_empty(),
        "{}: no stored pages to read",
        store.display()
    );
    if cold {
        let f = std::fs::File::open(&store)?;
        // SAFETY: plain advisory syscall on a valid descriptor.
        let rc = unsafe { libc::posix_fadvise(f.as_raw_fd(), 0, 0, libc::POSIX_FADV_DONTNEED) };
        anyhow::ensure!(rc == 0, "posix_fadvise failed: {rc}");
    }
    let next = AtomicU64::new(0);
    let bytes = AtomicU64::new(0);
    let t0 = Instant::now();
    std::thread::scope(|sc| -> Result<()> {
        let hs: Vec<_> = (0..threads.max(1))
            .map(|_| {
                sc.spawn(|| -> Result<()> {
                    let mut buf = vec![0f32; s.pyramid().page_samples()];
                    loop {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        if i >= pages {
                            return Ok(());
                        }
                        let id = candidates
                            [(fmix64(i ^ fmix64(seed)) % candidates.len() as u64) as usize];
                        s.read_page_into(id, &mut buf)?;
                        bytes.fetch_add(
                            s.entry(id).map_or(0, |e| e.stored_len as u64),
                            Ordering::Relaxed,
                        );
                    }
                })
            })
            .collect();
        for h in hs {
            h.join().expect("reader thread")?;
        }
        Ok(())
    })?;
    let secs = t0.elapsed().as_secs_f64();
    let b = bytes.load(Ordering::Relaxed) as f64;
    println!(
        "read-bench: threads {threads} pages {pages} cold {cold} seconds {secs:.3} pages_per_s {:.0} mb_per_s {:.1} page_bytes {}",
        pages as f64 / secs,
        b / secs / 1e6,
        s.header().page_raw_len()
    );
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    let r = match cli.command {
        None => strata_worker::cli::join(cli.join),
        Some(Command::ReadBench {
            store,
            threads,
            pages,
            cold,
            seed,
        }) => read_bench(store, threads, pages, cold, seed),
    };
    match r {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
