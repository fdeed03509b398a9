//! `bench-render --only-caster`: the CPU caster's paths side by side in one run (issue 14).
//!
//! Every configuration renders the same converged frame; the table gives the median frame
//! time, trilinear samples taken and per second, the fraction of lattice points skipped as
//! empty space, the bytes per voxel of the atlas slots, the largest difference from the
//! first configuration's image, and the speed-up over it.

use crate::{bonsai_scene, rmse, time_scene, Timed};
use anyhow::{Context, Result};
use indicatif::ProgressBar;
use std::path::{Path, PathBuf};
use std::time::Instant;
use strata_common::scene::{RenderSettings, Scene};
use strata_worker::macrocell::MacroCells;

/// What `--only-caster` runs on.
pub(crate) struct CasterArgs {
    /// The bonsai store.
    pub(crate) bonsai: PathBuf,
    /// Timed frames per configuration.
    pub(crate) frames: usize,
    /// Thread counts.
    pub(crate) threads: Vec<usize>,
    /// Only tables whose title contains this.
    pub(crate) case: String,
    /// Only paths whose label contains this.
    pub(crate) path_filter: String,
}

type Tweak = fn(&mut RenderSettings);

/// The caster's paths: the first is the reference of the comparison.
fn variants() -> Vec<(&'static str, Tweak)> {
    vec![
        ("scalar, f32 slots, brick skipping (before)", |s| {
            s.simd = false;
            s.compact_slots = false;
            s.macrocells = false;
        }),
        ("scalar, f32 slots + macrocells", |s| {
            s.simd = false;
            s.compact_slots = false;
        }),
        ("scalar, compact slots + macrocells", |s| s.simd = false),
        ("packets, f32 slots, brick skipping", |s| {
            s.compact_slots = false;
            s.macrocells = false;
        }),
        ("8-lane packets (AVX2), compact slots + macrocells", |s| {
            s.simd_lanes = 8
        }),
        ("packets, compact slots + macrocells (default)", |_| {}),
    ]
}

fn table(name: &str, base: impl Fn() -> Result<Scene>, args: &CasterArgs) -> Result<()> {
    if !name.contains(&args.case) {
        return Ok(());
    }
    let base = &base()?;
    println!("### {name}");
    println!();
    println!("| threads | path | frame (median of {}) | samples | samples/s | skipped | atlas B/voxel | max diff | speed-up |", args.frames);
    println!("|---|---|---|---|---|---|---|---|---|");
    for &n in &args.threads {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .context("thread pool")?;
        let mut first: Option<Timed> = None;
        for (label, tweak) in variants() {
            if !label.contains(&args.path_filter) {
                continue;
            }
            let mut s = base.clone();
            s.render.backend = strata_common::scene::Backend::Cpu;
            tweak(&mut s.render);
            let r = pool.install(|| time_scene(&s, args.frames))?;
            let (diff, speed) = match &first {
                Some(f) => (rmse(&r.image, &f.image).1, f.median / r.median),
                None => (0.0, 1.0),
            };
            let lattice = (r.samples + r.skipped).max(1);
            println!(
                "| {n} | {label} | {:.1} ms | {:.1} M | {:.0} M/s | {:.0} % | {} | {:.1e} | {:.2}× |",
                r.median * 1e3,
                r.samples as f64 / 1e6,
                r.samples as f64 / r.median / 1e6,
                100.0 * r.skipped as f64 / lattice as f64,
                r.bytes_per_voxel,
                diff,
                speed
            );
            if first.is_none() {
                first = Some(r);
            }
        }
    }
    println!();
    Ok(())
}

/// The demo scene (configs/demo.toml, generated on first use), with the volume's opacity.
/// The working directory's `configs/demo.toml` when there is one (a carried binary on
/// another machine, run from a copy of the repository), else the one beside the sources.
pub(crate) fn demo(opacity: f64) -> Result<Scene> {
    let here = Path::new("configs/demo.toml");
    let path = if here.is_file() {
        here.to_path_buf()
    } else {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/demo.toml")
    };
    let mut scene = strata_coordinator::overrides::load_scene(&path, &[], None)?;
    if let Some(spec) = &scene.synthetic {
        strata_coordinator::demo::ensure_synthetic(spec, &ProgressBar::hidden())?;
    }
    scene.volumes[0].opacity = opacity;
    Ok(scene)
}

/// Time to compute the macrocell ranges of one 64³ page (the cost a page pays as it enters
/// the atlas).
fn cell_cost() {
    let p = 64;
    let page: Vec<f32> = (0..p * p * p).map(|i| ((i * 7919) % 251) as f32).collect();
    let mut mc = MacroCells::new(p, 1);
    let n = 50;
    let t = Instant::now();
    for _ in 0..n {
        mc.compute(0, |i| page[i]);
        mc.classify(0, |lo, _| lo > 100.0);
    }
    let per = t.elapsed().as_secs_f64() / n as f64;
    println!(
        "Macrocell ranges and classification of one 64³ page: {:.2} ms ({} cells, {} bytes of ranges).",
        per * 1e3,
        mc.per_slot(),
        mc.per_slot() * 8
    );
    println!();
}

/// Runs the comparison.
pub(crate) fn run(args: &CasterArgs) -> Result<()> {
    println!("## CPU caster paths (issue 14)");
    println!();
    cell_cost();
    for (w, h) in [(1024, 1024), (1920, 1080)] {
        table(
            &format!("Bonsai 256³ u8, ParaView's setup, {w}×{h}"),
            || Ok(bonsai_scene(&args.bonsai, w, h)),
            args,
        )?;
    }
    table(
        "Demo survey (configs/demo.toml: slices and horizons, volume opacity 0), 1280×720",
        || demo(0.0),
        args,
    )?;
    table(
        "Demo survey with the translucent volume (opacity 0.06), 1280×720",
        || demo(0.06),
        args,
    )?;
    Ok(())
}
