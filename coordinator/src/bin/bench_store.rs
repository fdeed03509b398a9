//! `bench-store`: ingest and page-read benchmarks of the page store, beside the disk's own
//! sequential rates measured in the same run. Prints Markdown for docs/BENCHMARKS.md.
//!
//! Run with `cargo run --release --bin bench-store -- --dir /path/with/space`.

use anyhow::{bail, Context, Result};
use clap::Parser;
use indicatif::ProgressBar;
use std::fs::File;
use std::io::Write;
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;
use strata_common::filter::CoarsenFilter;
use strata_common::sample::SampleType;
use strata_common::store::PageStore;
use strata_coordinator::builder::{build_store, BuildOptions};
use strata_coordinator::source::GridSource;
use strata_coordinator::synth::{write_segy, SynthModel};

#[derive(Parser)]
#[command(about = "Page-store ingest and read benchmarks")]
struct Args {
    /// Scratch folder (needs about 3x the cube size free).
    #[arg(long)]
    dir: PathBuf,
    /// Raw f32 cube size (default 2 GiB).
    #[arg(long, num_args = 3, default_values_t = [1024u64, 1024, 512])]
    cube: Vec<u64>,
    /// SEG-Y cube size (default about 1.1 GiB of IEEE float).
    #[arg(long, num_args = 3, default_values_t = [768u64, 512, 700])]
    segy: Vec<u64>,
    /// Size of the cube used to measure the coarsening filters' error and cost.
    #[arg(long, num_args = 3, default_values_t = [256u64, 256, 256])]
    filter_cube: Vec<u64>,
    /// Keep the generated files.
    #[arg(long)]
    keep: bool,
}

fn drop_cache(p: &Path) -> Result<()> {
    let f = File::open(p)?;
    f.sync_all()?;
    // SAFETY: advisory syscall on a valid descriptor.
    let rc = unsafe { libc::posix_fadvise(f.as_raw_fd(), 0, 0, libc::POSIX_FADV_DONTNEED) };
    if rc != 0 {
        bail!("posix_fadvise failed: {rc}");
    }
    Ok(())
}

/// Runs a child to completion; returns (seconds, peak RSS in MiB, stdout).
fn run_child(cmd: &mut Command) -> Result<(f64, f64, String)> {
    let t0 = Instant::now();
    let child = cmd
        .stdout(std::process::Stdio::piped())
        .spawn()
        .context("spawn")?;
    let pid = child.id() as libc::pid_t;
    let mut out = String::new();
    if let Some(mut so) = child.stdout {
        use std::io::Read;
        so.read_to_string(&mut out)?;
    }
    let mut status = 0;
    // SAFETY: zeroed rusage is a valid value; wait4 on our own child.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    let r = unsafe { libc::wait4(pid, &mut status, 0, &mut ru) };
    let secs = t0.elapsed().as_secs_f64();
    if r != pid || !libc::WIFEXITED(status) || libc::WEXITSTATUS(status) != 0 {
        bail!("{cmd:?} failed (status {status}): {out}");
    }
    Ok((secs, ru.ru_maxrss as f64 / 1024.0, out))
}

fn sibling(name: &str) -> Result<PathBuf> {
    let exe = std::env::current_exe()?;
    let p = exe.with_file_name(name);
    if !p.exists() {
        bail!(
            "{} not built; run `cargo build --release` first",
            p.display()
        );
    }
    Ok(p)
}

fn main() -> Result<()> {
    let a = Args::parse();
    std::fs::create_dir_all(&a.dir)?;
    let coord = sibling("coordinator")?;
    let worker = sibling("worker")?;
    let gib = (1u64 << 30) as f64;
    println!("| measurement | value |\n|---|---|");

    // 1. The disk's own sequential rates.
    let dd = a.dir.join("dd.bin");
    let (ws, _, _) = run_child(Command::new("dd").args([
        "if=/dev/zero",
        &format!("of={}", dd.display()),
        "bs=8M",
        "count=256",
        "conv=fdatasync",
        "status=none",
    ]))?;
    drop_cache(&dd)?;
    let (rs, _, _) = run_child(Command::new("dd").args([
        &format!("if={}", dd.display()),
        "of=/dev/null",
        "bs=8M",
        "status=none",
    ]))?;
    std::fs::remove_file(&dd)?;
    let (disk_w, disk_r) = (2048.0 / ws, 2048.0 / rs);
    println!("| disk sequential write (dd 2 GiB, fdatasync) | {disk_w:.0} MiB/s |");
    println!("| disk sequential read (dd 2 GiB, cold) | {disk_r:.0} MiB/s |");

    // 2. A ≥ 2 GiB synthetic cube as a raw f32 file, then `ingest raw`.
    let dims = [a.cube[0], a.cube[1], a.cube[2]];
    let model = SynthModel::new(dims, 7)?;
    let raw = a.dir.join("cube.raw");
    let t0 = Instant::now();
    {
        let mut w = std::io::BufWriter::with_capacity(8 << 20, File::create(&raw)?);
        let dz = 16u64;
        let mut z = 0;
        while z < dims[2] {
            let n = dz.min(dims[2] - z);
            let mut buf = vec![0f32; (dims[0] * dims[1] * n) as usize];
            model.read_box([0, 0, z], [dims[0], dims[1], n], &mut buf)?;
            w.write_all(bytemuck::cast_slice(&buf))?;
            z += n;
        }
        w.flush()?;
    }
    let raw_bytes = std::fs::metadata(&raw)?.len() as f64;
    println!(
        "| generate synthetic raw cube {}x{}x{} f32 ({:.2} GiB) | {:.1} s |",
        dims[0],
        dims[1],
        dims[2],
        raw_bytes / gib,
        t0.elapsed().as_secs_f64()
    );
    drop_cache(&raw)?;
    let store = a.dir.join("cube.strata");
    let d = dims.map(|v| v.to_string());
    let (s, rss, _) = run_child(
        Command::new(&coord)
            .args(["-q", "ingest", "raw"])
            .arg(&raw)
            .args(["--dims", &d[0], &d[1], &d[2], "--dtype", "f32", "-o"])
            .arg(&store),
    )?;
    let out_bytes = std::fs::metadata(&store)?.len() as f64;
    println!("| ingest raw: time | {s:.1} s |");
    println!(
        "| ingest raw: input throughput | {:.0} MiB/s ({:.0}% of disk write) |",
        raw_bytes / s / 1048576.0,
        100.0 * raw_bytes / s / 1048576.0 / disk_w
    );
    println!(
        "| ingest raw: output written | {:.2} GiB ({:.0} MiB/s, {:.3}x input) |",
        out_bytes / gib,
        out_bytes / s / 1048576.0,
        out_bytes / raw_bytes
    );
    println!("| ingest raw: peak RSS | {rss:.0} MiB |");
    std::fs::remove_file(&raw)?;

    // 3. Random page reads of that store, cold, 1 and 2 threads.
    for threads in [1, 2] {
        let (_, _, out) = run_child(Command::new(&worker).args(["read-bench"]).arg(&store).args(
            [
                "--threads",
                &threads.to_string(),
                "--pages",
                "3000",
                "--cold",
                "--seed",
                &threads.to_string(),
            ],
        ))?;
        let f = |k: &str| {
            out.split_whitespace()
                .skip_while(|w| *w != k)
                .nth(1)
                .unwrap_or("?")
                .to_string()
        };
        println!("| random page reads, {threads} thread(s), cold (read+crc+decode 64³ f32 pages) | {} pages/s, {} MB/s |", f("pages_per_s"), f("mb_per_s"));
    }
    if !a.keep {
        std::fs::remove_file(&store)?;
    }

    // 4. A ≥ 1 GiB SEG-Y file, then `ingest segy`.
    let sd = [a.segy[0], a.segy[1], a.segy[2]];
    let sm = SynthModel::new(sd, 11)?;
    let sgy = a.dir.join("cube.sgy");
    let t0 = Instant::now();
    write_segy(&sm, &sgy)?;
    let sgy_bytes = std::fs::metadata(&sgy)?.len() as f64;
    println!(
        "| generate SEG-Y {}x{}x{} IEEE float ({:.2} GiB) | {:.1} s |",
        sd[0],
        sd[1],
        sd[2],
        sgy_bytes / gib,
        t0.elapsed().as_secs_f64()
    );
    drop_cache(&sgy)?;
    let sstore = a.dir.join("segy.strata");
    let (s, rss, _) = run_child(
        Command::new(&coord)
            .args(["-q", "ingest", "segy"])
            .arg(&sgy)
            .arg("-o")
            .arg(&sstore),
    )?;
    println!("| ingest segy: time | {s:.1} s |");
    println!(
        "| ingest segy: input throughput | {:.0} MiB/s ({:.0}% of disk write) |",
        sgy_bytes / s / 1048576.0,
        100.0 * sgy_bytes / s / 1048576.0 / disk_w
    );
    println!("| ingest segy: peak RSS | {rss:.0} MiB |");
    if !a.keep {
        std::fs::remove_file(&sgy)?;
        std::fs::remove_file(&sstore)?;
    }

    // 5. Coarsening filters: error and cost, side by side on one cube.
    let fd = [a.filter_cube[0], a.filter_cube[1], a.filter_cube[2]];
    let fm = SynthModel::new(fd, 3)?;
    println!("\n| filter | build time (s) | level | RMS(level)/RMS(level 0) | RMS(level - box-filter level)/RMS(level 0) |\n|---|---|---|---|---|");
    let mut stores = Vec::new();
    for f in [
        CoarsenFilter::Mean,
        CoarsenFilter::SignedRms,
        CoarsenFilter::MaxAbs,
    ] {
        let p = a.dir.join(format!("filter-{}.strata", f.name()));
        let mut o = BuildOptions::volume("f", SampleType::F32);
        o.filter = f;
        let t0 = Instant::now();
        build_store(&fm, &p, &o, &ProgressBar::hidden())?;
        stores.push((f, t0.elapsed().as_secs_f64(), PageStore::open(&p)?, p));
    }
    let grids: Vec<Vec<Vec<f32>>> = stores
        .iter()
        .map(|(_, _, s, _)| {
            (0..s.pyramid().level_count())
                .map(|l| strata_coordinator::inspect::level_grid(s, l))
                .collect::<Result<Vec<_>, _>>()
        })
        .collect::<Result<_, _>>()?;
    let rms = |v: &[f32]| {
        (v.iter()
            .filter(|x| !x.is_nan())
            .map(|&x| (x as f64).powi(2))
            .sum::<f64>()
            / v.len() as f64)
            .sqrt()
    };
    let r0 = rms(&grids[0][0]);
    for (k, (f, secs, _, _)) in stores.iter().enumerate() {
        for l in 1..grids[k].len().min(4) {
            let diff: Vec<f32> = grids[k][l]
                .iter()
                .zip(&grids[0][l])
                .map(|(a, b)| a - b)
                .collect();
            println!(
                "| {} | {secs:.2} | {l} | {:.3} | {:.3} |",
                f.name(),
                rms(&grids[k][l]) / r0,
                rms(&diff) / r0
            );
        }
    }
    for (_, _, _, p) in stores {
        std::fs::remove_file(p)?;
    }
    Ok(())
}
