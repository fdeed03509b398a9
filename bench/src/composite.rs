//! `bench-composite`: sort-last compositing over loopback QUIC between worker processes,
//! side by side with the loopback QUIC throughput measured in the same run and with IceT
//! 2.2's numbers on this machine (`../shared/baselines/RESULTS.md`).
//!
//! For each process count p and transport (shared memory or loopback QUIC,
//! `--transports`), one cluster of p local worker processes is started once;
//! every configuration (algorithm × wire format × density) then runs `--frames` frames
//! (plus one warm-up). Workers draw IceT `SimpleTiming`-like images instead of rendering:
//! dense (every pixel active, no interlacing, as `-dense-images`) or sparse (each rank's
//! box covers `--sparse-coverage` of the frame, interlacing on). The compositing time is
//! measured as IceT's frame time is: from the last worker finishing its image to the last
//! final piece arriving at the coordinator (exchange + gather).
//!
//! ```text
//! cargo build --release -p strata-bench && ./target/release/bench-composite
//! ```

use anyhow::{Context, Result};
use clap::Parser;
use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};
use strata_common::composite::{Algorithm, WireFormat};
use strata_common::scene::{Scene, Transport};
use strata_common::wire::{CompositeChoice, FrameSource};
use strata_coordinator::cluster::{Cluster, ClusterOptions};
use strata_net::{transport, Identity, NetConfig};

#[derive(Parser)]
#[command(name = "bench-composite", version, about)]
#[command(args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    worker: Option<Sub>,
    /// Process counts.
    #[arg(long, value_delimiter = ',', default_values_t = [2usize, 4, 8])]
    procs: Vec<usize>,
    /// Image size.
    #[arg(long, default_value = "1920x1080")]
    size: String,
    /// Timed frames per configuration (the median is reported).
    #[arg(long, default_value_t = 10)]
    frames: usize,
    /// Transports to compare (`cluster.transport`): `shm` (shared memory between the
    /// local processes), `quic` (loopback QUIC) and `quic-lz4` (loopback QUIC with
    /// `composite.lz4`); `quic@4000` starts QUIC datagrams at 4000 bytes
    /// (`cluster.quic_mtu`).
    #[arg(long, value_delimiter = ',', default_values_t = ["shm".to_string(), "quic".to_string()])]
    transports: Vec<String>,
    /// Also measure the loopback QUIC rate starting at these datagram sizes
    /// (`cluster.quic_mtu`), e.g. `1452,4000,9000`.
    #[arg(long, value_delimiter = ',')]
    loopback_mtus: Vec<u16>,
    /// Fraction of the frame each rank's box covers in the sparse case.
    #[arg(long, default_value_t = 0.2)]
    sparse_coverage: f32,
    /// Folder for the scratch survey the workers open.
    #[arg(long, default_value = "target/bench-composite")]
    dir: PathBuf,
    /// Write the measurements as JSON lines here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Write an SVG chart (time per configuration against IceT) here.
    #[arg(long)]
    svg: Option<PathBuf>,
}

#[derive(clap::Subcommand)]
enum Sub {
    /// (internal) run as a worker of the benchmark's cluster.
    Worker(strata_worker::cli::JoinArgs),
}

/// IceT 2.2 SimpleTiming medians (ms) on this machine, from RESULTS.md, for its automatic
/// strategy (radix-kr) with ordered float blending at 1920x1080: (p, dense, sparse).
const ICET: [(usize, f64, f64); 3] = [(2, 20.89, 6.74), (4, 26.82, 9.83), (8, 49.1, 13.79)];

/// The frame IceT's numbers are of, and the sparse coverage compared with them (the
/// default `--sparse-coverage`): other runs print no IceT column.
const ICET_SIZE: (u32, u32) = (1920, 1080);
const ICET_SPARSE_COVERAGE: f32 = 0.2;

#[derive(serde::Serialize, Clone)]
struct Row {
    procs: usize,
    transport: String,
    density: &'static str,
    algorithm: String,
    wire: &'static str,
    /// Median compositing time (exchange + gather), ms.
    composite_ms: f64,
    /// Median compositing time with the coordinator's assembly of the image (what IceT's
    /// frame time covers: its collection lands in the display rank's image), ms.
    assembled_ms: f64,
    /// Median over frames of the slowest rank's encode + exchange + blend, ms.
    exchange_ms: f64,
    encode_ms: f64,
    blend_ms: f64,
    /// Median of the slowest rank's final hand-off (its encode straight into the gather
    /// segment, or its encode and send over QUIC), ms.
    final_ms: f64,
    /// Median coordinator time reading and checking the final pieces, ms.
    collect_ms: f64,
    /// Median coordinator time assembling the image (after `composite_ms`), ms.
    assemble_ms: f64,
    /// Mean bytes a rank sent in the exchange.
    bytes_per_rank: f64,
    /// Lower bound N(1 - 1/p) with N the dense image in this wire format.
    bound_bytes: f64,
    gather_bytes: f64,
    /// Time to move N(1 - 1/p) at the measured loopback rate, ms.
    bound_ms: f64,
    icet_ms: f64,
}

fn median(v: Vec<f64>) -> f64 {
    strata_common::stats::median(&v)
}

/// MiB/s of one QUIC stream between two endpoints on 127.0.0.1 (256 MiB in 1 MiB writes).
async fn loopback_rate(net: &NetConfig) -> Result<f64> {
    let id = Identity::generate()?;
    let server = transport::endpoint("127.0.0.1:0".parse()?, &id, net)?;
    let addr = server.local_addr()?;
    let total: usize = 256 << 20;
    let rx = tokio::spawn(async move {
        let conn = server.accept().await.context("no connection")?.await?;
        let mut s = conn.accept_uni().await?;
        let mut n = 0usize;
        while let Some(c) = s.read_chunk(usize::MAX, true).await? {
            n += c.bytes.len();
        }
        anyhow::Ok(n)
    });
    let cid = Identity::generate()?;
    let client = transport::endpoint("127.0.0.1:0".parse()?, &cid, net)?;
    let conn =
        transport::connect(&client, addr, id.fingerprint, net, Duration::from_secs(10)).await?;
    let chunk = vec![7u8; 1 << 20];
    let t = Instant::now();
    let mut s = conn.open_uni().await?;
    for _ in 0..total / chunk.len() {
        s.write_all(&chunk).await?;
    }
    s.finish()?;
    let n = rx.await??;
    let secs = t.elapsed().as_secs_f64();
    anyhow::ensure!(n == total, "received {n} of {total} bytes");
    Ok(total as f64 / secs / (1 << 20) as f64)
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    strata_worker::node::retain_freed_memory();
    if let Some(Sub::Worker(a)) = cli.worker {
        tracing_subscriber::fmt()
            .with_env_filter(tracing_subscriber::EnvFilter::new("warn"))
            .with_writer(std::io::stderr)
            .init();
        return strata_worker::cli::join(a);
    }
    let (w, h) = strata_coordinator::overrides::parse_size(&cli.size)?;
    let pb = indicatif::ProgressBar::hidden();
    let survey = cli.dir.join("survey");
    if !survey.join("scene.toml").exists() {
        strata_coordinator::synth::synth(&survey, [32, 32, 32], 1, false, &pb)?;
    }
    let scene_path = survey.join("scene.toml");
    let mut scene = Scene::parse(&scene_path, &std::fs::read_to_string(&scene_path)?)?;
    scene.render.width = w;
    scene.render.height = h;
    scene.render.atlas_mb = 16;
    scene.render.horizon_atlas_mb = 8;
    scene.render.cache_mb = 64;
    let camera = scene.camera.clone().context("synth writes a camera")?;

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let net = NetConfig::default();
    let rate = rt.block_on(loopback_rate(&net))?;
    println!("loopback QUIC, one stream, 256 MiB: {rate:.0} MiB/s");
    // What segmentation offload gives (on by default), measured in the same run.
    let no_gso = NetConfig {
        segmentation_offload: false,
        ..NetConfig::default()
    };
    match rt.block_on(loopback_rate(&no_gso)) {
        Ok(r) => println!("  without segmentation offload: {r:.0} MiB/s"),
        Err(e) => println!("  without segmentation offload: {e:#}"),
    }
    for &mtu in &cli.loopback_mtus {
        let n = NetConfig {
            initial_mtu: mtu,
            ..NetConfig::default()
        };
        match rt.block_on(loopback_rate(&n)) {
            Ok(r) => println!("  initial MTU {mtu}: {r:.0} MiB/s"),
            Err(e) => println!("  initial MTU {mtu}: {e:#}"),
        }
    }
    let mut rows = Vec::new();
    // (transport, LZ4 on QUIC pieces, first QUIC datagram size, name in the tables)
    let transports: Vec<(Transport, bool, u16, String)> = cli
        .transports
        .iter()
        .map(|t| {
            let (kind, mtu) = match t.split_once('@') {
                Some((k, m)) => match m.parse::<u16>() {
                    Ok(m) if (1200..=65527).contains(&m) => (k, m),
                    _ => anyhow::bail!(
                        "--transports: {t:?}: the size after @ must be 1200..=65527 bytes"
                    ),
                },
                None => (t.as_str(), 1200),
            };
            match kind {
                "shm" => Ok((Transport::Shm, false, mtu, t.clone())),
                "quic" => Ok((Transport::Quic, false, mtu, t.clone())),
                "quic-lz4" => Ok((Transport::Quic, true, mtu, t.clone())),
                "auto" => Ok((Transport::Auto, false, mtu, t.clone())),
                other => anyhow::bail!(
                    "--transports: {other:?} is not shm, quic, quic-lz4 or auto (each with an optional @MTU)"
                ),
            }
        })
        .collect::<Result<_>>()?;
    for &p in &cli.procs {
        for (transport, lz4, mtu, tname) in transports.iter().cloned() {
            let mut opts = ClusterOptions::from_scene(&scene, Some(p))?;
            opts.worker_threads = 1;
            opts.transport = transport;
            opts.quic_mtu = mtu;
            // LZ4 is a run setting: the workers' peer readers accept compressed pieces only
            // in a run set up with it.
            let mut run_scene = scene.clone();
            run_scene.composite.lz4 = lz4;
            let rows_p = rt.block_on(async {
            let mut cluster = Cluster::start(&run_scene, opts).await?;
            let mut rows = Vec::new();
            for (density, coverage, interlace) in [
                ("dense", 1.0f32, false),
                ("sparse", cli.sparse_coverage, true),
            ] {
                for algorithm in [
                    Algorithm::DirectSend,
                    Algorithm::BinarySwap,
                    Algorithm::RadixK,
                    Algorithm::Gather,
                ] {
                    for wire in [WireFormat::F32, WireFormat::F16] {
                        let choice = CompositeChoice {
                            algorithm,
                            k: vec![8],
                            interlace,
                            format: wire,
                            lz4,
                        };
                        let mut comp = Vec::new();
                        let mut exch = Vec::new();
                        let mut enc = Vec::new();
                        let mut blend = Vec::new();
                        let mut fin = Vec::new();
                        let mut collect = Vec::new();
                        let mut asm = Vec::new();
                        let mut with_asm = Vec::new();
                        let mut bytes = 0.0;
                        let mut gather = 0.0;
                        for f in 0..=cli.frames {
                            let r = cluster
                                .frame(
                                    &camera,
                                    w,
                                    h,
                                    &choice,
                                    FrameSource::Synthetic {
                                        coverage,
                                        seed: 12345 + f as u64,
                                    },
                                )
                                .await?;
                            // A worker given up on would make the rest of the rows a
                            // smaller p: refuse to report them.
                            if let Some(l) = r.lost.first() {
                                anyhow::bail!(
                                    "p={p} {tname}: lost {} during the benchmark: {}",
                                    l.worker,
                                    l.reason
                                );
                            }
                            if f == 0 {
                                continue; // warm-up
                            }
                            comp.push(r.composite_s * 1e3);
                            let slowest = r
                                .stats
                                .iter()
                                .map(|s| s.encode_s + s.exchange_s + s.blend_s)
                                .fold(0.0, f64::max);
                            exch.push(slowest * 1e3);
                            enc.push(r.stats.iter().map(|s| s.encode_s).fold(0.0, f64::max) * 1e3);
                            blend.push(r.stats.iter().map(|s| s.blend_s).fold(0.0, f64::max) * 1e3);
                            fin.push(r.stats.iter().map(|s| s.gather_s).fold(0.0, f64::max) * 1e3);
                            collect.push(r.collect_s * 1e3);
                            asm.push(r.assemble_s * 1e3);
                            with_asm.push((r.composite_s + r.assemble_s) * 1e3);
                            bytes += r.stats.iter().map(|s| s.bytes_sent as f64).sum::<f64>()
                                / p as f64;
                            gather += r.gather_bytes as f64;
                        }
                        let n = cli.frames as f64;
                        let image_bytes = (w as f64) * (h as f64) * wire.bytes_per_pixel() as f64;
                        let bound = image_bytes * (1.0 - 1.0 / p as f64);
                        // IceT's numbers are of its own frame and coverage only.
                        let comparable = (w, h) == ICET_SIZE
                            && (coverage >= 1.0 || coverage == ICET_SPARSE_COVERAGE);
                        let icet = ICET
                            .iter()
                            .find(|i| i.0 == p && comparable)
                            .map_or(f64::NAN, |i| if coverage >= 1.0 { i.1 } else { i.2 });
                        let row = Row {
                            procs: p,
                            transport: tname.clone(),
                            density,
                            algorithm: algorithm.to_string(),
                            wire: if wire == WireFormat::F32 { "f32" } else { "f16" },
                            composite_ms: median(comp),
                            assembled_ms: median(with_asm),
                            exchange_ms: median(exch),
                            encode_ms: median(enc),
                            blend_ms: median(blend),
                            final_ms: median(fin),
                            collect_ms: median(collect),
                            assemble_ms: median(asm),
                            bytes_per_rank: bytes / n,
                            bound_bytes: bound,
                            gather_bytes: gather / n,
                            bound_ms: bound / (rate * (1 << 20) as f64) * 1e3,
                            icet_ms: icet,
                        };
                        eprintln!(
                            "p={p} {tname} {density} {} {}: {:.1} ms (exchange {:.1} ms [encode {:.1}, blend {:.1}], final {:.1} ms, collect {:.1} ms, assemble {:.1} ms, bound {:.1} ms), {:.1} MB/rank",
                            row.algorithm, row.wire, row.composite_ms, row.exchange_ms, row.encode_ms, row.blend_ms, row.final_ms, row.collect_ms, row.assemble_ms, row.bound_ms,
                            row.bytes_per_rank / 1e6
                        );
                        rows.push(row);
                    }
                }
            }
            cluster.shutdown().await;
            anyhow::Ok(rows)
        })?;
            rows.extend(rows_p);
        }
    }
    drop(rt);

    println!(
        "\n| p | transport | image | algorithm | wire | compositing ms | with assembly ms | exchange ms (slowest rank) | encode ms | blend ms | MB sent/rank | bound N(1-1/p) MB | bound at loopback rate ms | MB gathered | IceT ms | ours (with assembly) / IceT |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for r in &rows {
        println!(
            "| {} | {} | {} | {} | {} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.2} | {} | {} | {:.2} | {:.1} | {:.2} |",
            r.procs,
            r.transport,
            r.density,
            r.algorithm,
            r.wire,
            r.composite_ms,
            r.assembled_ms,
            r.exchange_ms,
            r.encode_ms,
            r.blend_ms,
            r.bytes_per_rank / 1e6,
            if r.density == "dense" { format!("{:.2}", r.bound_bytes / 1e6) } else { "-".into() },
            if r.density == "dense" { format!("{:.1}", r.bound_ms) } else { "-".into() },
            r.gather_bytes / 1e6,
            r.icet_ms,
            r.assembled_ms / r.icet_ms
        );
    }
    // Sparse against dense, same p / algorithm / wire.
    println!("\n| p | transport | algorithm | wire | dense ms | sparse ms | dense / sparse |");
    println!("|---|---|---|---|---|---|---|");
    for d in rows.iter().filter(|r| r.density == "dense") {
        if let Some(s) = rows.iter().find(|s| {
            s.density == "sparse"
                && s.procs == d.procs
                && s.transport == d.transport
                && s.algorithm == d.algorithm
                && s.wire == d.wire
        }) {
            println!(
                "| {} | {} | {} | {} | {:.1} | {:.1} | {:.2} |",
                d.procs,
                d.transport,
                d.algorithm,
                d.wire,
                d.composite_ms,
                s.composite_ms,
                d.composite_ms / s.composite_ms
            );
        }
    }
    if let Some(p) = &cli.json {
        let mut f = std::fs::File::create(p)?;
        writeln!(f, "{}", serde_json::json!({"loopback_mib_s": rate}))?;
        for r in &rows {
            writeln!(f, "{}", serde_json::to_string(r)?)?;
        }
    }
    if let Some(p) = &cli.svg {
        std::fs::write(p, svg(&rows, (w, h)))?;
        println!("\nwrote {}", p.display());
    }
    Ok(())
}

/// A grouped bar chart: compositing time (with assembly) of every configuration, with
/// IceT's as a line.
fn svg(rows: &[Row], (w, h): (u32, u32)) -> String {
    let bar = 9.0;
    let gap = 14.0;
    let left = 60.0;
    let height = 320.0;
    let top = 30.0;
    let max = rows
        .iter()
        .map(|r| r.assembled_ms.max(r.icet_ms))
        .filter(|v| v.is_finite())
        .fold(1.0, f64::max)
        * 1.1;
    let mut x = left;
    let mut body = String::new();
    let colors = |r: &Row| match (r.algorithm.as_str(), r.wire) {
        ("direct-send", "f32") => "#1f77b4",
        ("direct-send", _) => "#aec7e8",
        ("binary-swap", "f32") => "#d62728",
        ("binary-swap", _) => "#ff9896",
        ("radix-k", "f32") => "#2ca02c",
        ("radix-k", _) => "#98df8a",
        (_, "f32") => "#9467bd",
        _ => "#c5b0d5",
    };
    // IceT's line over a group's bars, drawn once the group's width is known.
    let icet_line = |start: f64, end: f64, icet: f64| {
        if icet.is_finite() {
            let y = top + height - icet / max * height;
            format!(
                "<line x1='{:.1}' x2='{:.1}' y1='{y:.1}' y2='{y:.1}' stroke='black' stroke-dasharray='3,2'/>\n",
                start - 2.0,
                end + 2.0
            )
        } else {
            String::new()
        }
    };
    let mut group_icet = f64::NAN;
    let mut group_start = x;
    let mut last: Option<(usize, &str, &str)> = None;
    for r in rows {
        let key = Some((r.procs, r.transport.as_str(), r.density));
        if last.is_some() && last != key {
            body += &icet_line(group_start, x, group_icet);
            x += gap;
            group_start = x;
        }
        if last != key {
            body += &format!(
                "<text x='{:.1}' y='{:.1}' font-size='9'>p={} {}</text><text x='{:.1}' y='{:.1}' font-size='9'>{}</text>\n",
                group_start,
                top + height + 14.0,
                r.procs,
                r.density,
                group_start,
                top + height + 25.0,
                r.transport
            );
            group_icet = r.icet_ms;
        }
        let hgt = r.assembled_ms / max * height;
        body += &format!(
            "<rect x='{x:.1}' y='{:.1}' width='{:.1}' height='{hgt:.1}' fill='{}'><title>{} {} {}: {:.1} ms</title></rect>\n",
            top + height - hgt,
            bar - 1.0,
            colors(r),
            r.algorithm,
            r.wire,
            r.density,
            r.assembled_ms
        );
        x += bar;
        last = key;
    }
    body += &icet_line(group_start, x, group_icet);
    let width = x + 200.0;
    let mut axis = String::new();
    for i in 0..=5 {
        let v = max * i as f64 / 5.0;
        let y = top + height - v / max * height;
        axis += &format!(
            "<text x='{:.1}' y='{:.1}' font-size='10' text-anchor='end'>{v:.0}</text><line x1='{left}' x2='{:.1}' y1='{y:.1}' y2='{y:.1}' stroke='#ddd'/>\n",
            left - 4.0,
            y + 3.0,
            x
        );
    }
    let legend: String = [
        ("direct-send f32", "#1f77b4"),
        ("direct-send f16", "#aec7e8"),
        ("binary-swap f32", "#d62728"),
        ("binary-swap f16", "#ff9896"),
        ("radix-k f32", "#2ca02c"),
        ("radix-k f16", "#98df8a"),
        ("gather f32", "#9467bd"),
        ("gather f16", "#c5b0d5"),
    ]
    .iter()
    .enumerate()
    .map(|(i, (n, c))| {
        format!(
            "<rect x='{:.1}' y='{:.1}' width='10' height='10' fill='{c}'/><text x='{:.1}' y='{:.1}' font-size='11'>{n}</text>\n",
            x + 20.0,
            top + 14.0 * i as f64,
            x + 34.0,
            top + 14.0 * i as f64 + 9.0
        )
    })
    .collect();
    format!(
        "<svg xmlns='http://www.w3.org/2000/svg' width='{width:.0}' height='{:.0}' font-family='sans-serif'>\n<rect width='100%' height='100%' fill='white'/>\n<text x='{left}' y='16' font-size='13'>Compositing time per frame with the assembly at {w}x{h}, ms (dashed: IceT 2.2 radix-kr, float, at 1920x1080)</text>\n{axis}{body}{legend}<text x='{:.1}' y='{:.1}' font-size='11'>- - IceT</text>\n</svg>\n",
        top + height + 30.0,
        x + 20.0,
        top + 14.0 * 8.0 + 9.0
    )
}
