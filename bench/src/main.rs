//! `bench-render`: frame times, samples/s and the cost of accuracy for the CPU ray caster.
//!
//! * the bonsai CT (256³ u8) with ParaView's baseline transfer function and camera
//!   (`../shared/baselines/paraview_volume.py`), at 1024² and 1920×1080;
//! * accuracy against time: step, early termination, adaptive step and LOD tolerance, each
//!   compared with a high-accuracy reference image;
//! * the engine's CPU and GPU backends on the same frames (bonsai, and a synthetic survey
//!   with three horizons; 1920×1080, 3840×2160);
//! * a large synthetic survey with three horizons under a 1 GiB cache: rounds to converge,
//!   pages loaded, hit rate.
//!
//! Run in release mode; the exact command and the numbers live in docs/BENCHMARKS.md.

use anyhow::{Context, Result};
use clap::Parser;
use indicatif::ProgressBar;
use std::path::{Path, PathBuf};
use std::time::Instant;
use strata_common::image::Rgba;
use strata_common::sample::SampleType;
use strata_common::scene::{Camera, RenderSettings, Scene, SyntheticSpec, VolumeLayer};
use strata_coordinator::builder::{build_store, BuildOptions};
use strata_coordinator::source::RawSource;
use strata_worker::engine::Engine;

#[derive(Parser)]
#[command(name = "bench-render", about)]
struct Cli {
    /// Scratch folder (stores are built here).
    #[arg(long, default_value = "/tmp/strata-bench")]
    dir: PathBuf,
    /// Timed frames per configuration (median reported).
    #[arg(long, default_value_t = 5)]
    frames: usize,
    /// Skip the large synthetic survey.
    #[arg(long)]
    no_survey: bool,
    /// Samples per axis of the synthetic survey (default ≈ 4.5 GiB of f32).
    #[arg(long, num_args = 3, default_values_t = [1120u64, 1000, 1000])]
    survey_size: Vec<u64>,
    /// Only the synthetic survey.
    #[arg(long)]
    only_survey: bool,
    /// Skip the CPU-against-GPU backend comparison.
    #[arg(long)]
    no_gpu: bool,
    /// Only the CPU-against-GPU backend comparison.
    #[arg(long)]
    only_backends: bool,
    /// Only the CPU caster's paths (issue 14): bonsai and demo frames on 1 and 2 threads
    /// with macrocells and compact slots on and off.
    #[arg(long)]
    only_caster: bool,
    /// Only what each effect costs, used and unused (specialised code against the effect
    /// compiled in and the general path; issue 12).
    #[arg(long)]
    only_effects: bool,
    /// Frame size of `--only-effects`.
    #[arg(long, num_args = 2, default_values_t = [640u32, 360])]
    effects_size: Vec<u32>,
    /// `--only-effects`: only the GPU caster's table.
    #[arg(long)]
    effects_gpu_only: bool,
    /// CPU caster threads of `--only-effects`.
    #[arg(long, default_value_t = 1)]
    effects_threads: usize,
    /// `--only-effects`: only the rows of these effects (e.g. `preintegrated,shading`).
    #[arg(long, value_delimiter = ',')]
    effects_only: Vec<String>,
    /// Threads for `--only-caster` (each a separate rayon pool).
    #[arg(long, value_delimiter = ',', default_values_t = [1usize, 2])]
    threads: Vec<usize>,
    /// `--only-caster`: only the tables whose title contains this, and only the paths whose
    /// label contains `--path-filter`.
    #[arg(long, default_value = "")]
    case: String,
    /// See `--case`.
    #[arg(long, default_value = "")]
    path_filter: String,
    /// The bonsai raw file.
    #[arg(long)]
    bonsai: Option<PathBuf>,
    /// Samples per axis of the synthetic survey (volume + 3 horizons) in the backend
    /// comparison (1120 1000 1000 is the 4 GiB survey).
    #[arg(long, num_args = 3, default_values_t = [256u64, 256, 256])]
    backends_survey_size: Vec<u64>,
}

fn bonsai_path(cli: &Cli) -> PathBuf {
    cli.bonsai.clone().unwrap_or_else(|| {
        PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/data/real/volumes/bonsai/bonsai_256x256x256_uint8.raw")
    })
}

fn bonsai_store(cli: &Cli) -> Result<PathBuf> {
    bonsai_store_at(
        &bonsai_path(cli),
        &cli.dir,
        "bonsai",
        strata_common::geo::Affine3::IDENTITY,
    )
}

/// `DIR/NAME.strata` built once from the bonsai raw file, placed by `transform`.
pub(crate) fn bonsai_store_at(
    raw: &Path,
    dir: &Path,
    name: &str,
    transform: strata_common::geo::Affine3,
) -> Result<PathBuf> {
    let out = dir.join(format!("{name}.strata"));
    if !out.exists() {
        let src = RawSource::open(raw, [256, 256, 256], SampleType::U8, false)?;
        let mut o = BuildOptions::volume(name, SampleType::U8);
        o.transform = transform;
        build_store(&src, &out, &o, &ProgressBar::hidden())?;
    }
    Ok(out)
}

/// ParaView's baseline setup: viridis over [0, 255], opacity 0 up to 10 % then to 0.5,
/// camera at centre + 1.8 × diagonal along (1, 0.6, 0.8), up +z, 30°.
pub(crate) fn bonsai_scene(store: &Path, w: u32, h: u32) -> Scene {
    let c = 127.5;
    let diag = (3.0f64).sqrt() * 255.0;
    let d: [f64; 3] = [1.0, 0.6, 0.8];
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    Scene {
        volumes: vec![VolumeLayer {
            store: store.to_path_buf(),
            colormap: "viridis".into(),
            window: Some([0.0, 255.0]),
            opacity: 1.0,
            opacity_points: Some(vec![[0.0, 0.0], [0.1, 0.0], [1.0, 0.5]]),
            slices: Vec::new(),
        }],
        horizons: vec![],
        camera: Some(Camera {
            eye: [0, 1, 2].map(|i| c + d[i] / n * 1.8 * diag),
            target: [c; 3],
            up: [0.0, 0.0, 1.0],
            fov_deg: 30.0,
        }),
        render: RenderSettings {
            width: w,
            height: h,
            z_down: false,
            ..RenderSettings::default()
        },
        synthetic: None,
        composite: Default::default(),
        cluster: Default::default(),
        wall: None,
    }
}

mod caster;
mod effects;
use caster::CasterArgs;

pub(crate) struct Timed {
    pub(crate) median: f64,
    pub(crate) samples: u64,
    pub(crate) skipped: u64,
    pub(crate) rays: u64,
    /// Bytes per voxel of the CPU atlas slots (0 on the GPU).
    pub(crate) bytes_per_voxel: usize,
    pub(crate) image: Vec<Rgba>,
}

/// Converges once (batch), then times `frames` frames with everything resident.
pub(crate) fn time_scene(scene: &Scene, frames: usize) -> Result<Timed> {
    let mut e = Engine::new(scene)?;
    let view = e.view(scene.render.width, scene.render.height)?;
    let region = e.scene_region();
    e.render_batch(&view, &region)?;
    let mut times = Vec::new();
    let mut last = None;
    for _ in 0..frames.max(1) {
        let f = e.render_frame(&view, &region)?;
        times.push(f.seconds);
        last = Some(f);
    }
    let f = last.unwrap();
    Ok(Timed {
        median: strata_common::stats::median(&times),
        samples: f.stats.samples,
        skipped: f.stats.skipped,
        rays: f.stats.rays,
        bytes_per_voxel: e.cpu_atlas_bytes_per_voxel().unwrap_or(0),
        image: f.image.to_full(),
    })
}

pub(crate) fn rmse(a: &[Rgba], b: &[Rgba]) -> (f64, f64) {
    let mut s = 0.0f64;
    let mut m = 0.0f64;
    for (p, q) in a.iter().zip(b) {
        for c in 0..4 {
            let d = (p[c] - q[c]) as f64;
            s += d * d;
            m = m.max(d.abs());
        }
    }
    ((s / (a.len() * 4) as f64).sqrt(), m)
}

/// The pixels of `a` and `b` (`w` wide) that differ by more than `tol` in some channel:
/// how many, and the worst one's position and both values (for knife-edge outliers).
fn outliers(a: &[Rgba], b: &[Rgba], w: u32, tol: f32) -> String {
    let mut n = 0;
    let mut worst: Option<(f32, usize)> = None;
    for (i, (p, q)) in a.iter().zip(b).enumerate() {
        let d = (0..4).map(|c| (p[c] - q[c]).abs()).fold(0.0f32, f32::max);
        if d > tol {
            n += 1;
            if worst.is_none_or(|(m, _)| d > m) {
                worst = Some((d, i));
            }
        }
    }
    match worst {
        None => format!("0 px > {tol:e}"),
        Some((_, i)) => {
            let f = |p: &Rgba| format!("({:.4}, {:.4}, {:.4}, {:.4})", p[0], p[1], p[2], p[3]);
            format!(
                "{n} px > {tol:e}; worst at ({}, {}): {} against {}",
                i as u32 % w,
                i as u32 / w,
                f(&a[i]),
                f(&b[i])
            )
        }
    }
}

fn peak_rss_mib() -> f64 {
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: getrusage writes into the struct we own.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut ru) };
    ru.ru_maxrss as f64 / 1024.0
}

fn bonsai(cli: &Cli) -> Result<()> {
    let store = bonsai_store(cli)?;
    println!("## Bonsai 256³ u8, ParaView's transfer function and camera, step 1 voxel");
    println!();
    println!("| image | frame (median of {}) | trilinear samples | samples/s | rays | vs ParaView 'Ray Cast Only' 1939 ms / 'Smart' 1539 ms (1024², 1 rank) |", cli.frames);
    println!("|---|---|---|---|---|---|");
    for (w, h) in [(1024, 1024), (1920, 1080)] {
        let t = time_scene(&bonsai_scene(&store, w, h), cli.frames)?;
        let vs = if w == 1024 {
            format!("{:.1}× / {:.1}× faster", 1.939 / t.median, 1.539 / t.median)
        } else {
            "-".into()
        };
        println!(
            "| {w}×{h} | {:.1} ms | {} | {:.0} M/s | {} | {vs} |",
            t.median * 1e3,
            t.samples,
            t.samples as f64 / t.median / 1e6,
            t.rays
        );
    }
    println!();

    // Accuracy against time.
    println!("## What accuracy costs (bonsai, 1024²; error against step 0.25, no early termination, fixed step, τ = 0.5)");
    println!();
    let mut reference = bonsai_scene(&store, 1024, 1024);
    reference.render.step = 0.25;
    reference.render.early_termination = 1.0;
    reference.render.adaptive_step = false;
    reference.render.tau = 0.5;
    let r = time_scene(&reference, 1)?;
    println!("reference: {:.0} ms, {} samples", r.median * 1e3, r.samples);
    println!();
    println!("| setting | frame ms | samples | RMSE | max abs error |");
    println!("|---|---|---|---|---|");
    type Tweak = fn(&mut RenderSettings);
    let variants: Vec<(&str, Tweak)> = vec![
        ("default (step 1, ERT 0.99, adaptive, τ 0.5)", |_| {}),
        ("step 0.5", |s| s.step = 0.5),
        ("step 2", |s| s.step = 2.0),
        ("ERT off (1.0)", |s| s.early_termination = 1.0),
        ("ERT 0.95", |s| s.early_termination = 0.95),
        ("fixed step (no adaptive)", |s| s.adaptive_step = false),
        ("τ = 2 px", |s| s.tau = 2.0),
        ("τ = 4 px", |s| s.tau = 4.0),
        ("no empty-space skipping", |s| {
            s.empty_space_skipping = false
        }),
        ("gradient shading on", |s| s.volume_shading = true),
    ];
    for (name, f) in variants {
        let mut s = bonsai_scene(&store, 1024, 1024);
        f(&mut s.render);
        let t = time_scene(&s, cli.frames)?;
        let (e, m) = rmse(&t.image, &r.image);
        println!(
            "| {name} | {:.1} | {} | {:.5} | {:.4} |",
            t.median * 1e3,
            t.samples,
            e,
            m
        );
    }
    println!();
    Ok(())
}

/// The engine's two backends on the same frame, same run: the CPU caster (rayon) and the
/// wgpu caster (a hardware GPU, or Mesa's lavapipe when there is none), both through the
/// atlas, page tables and feedback. For each: the cold batch (time to converge, rounds, bytes
/// uploaded to the device), the converged frame (median time, samples/s), the feedback bytes
/// read back per frame, and the GPU image's largest difference from the CPU image.
/// The synthetic survey of `size` (generated once into the scratch folder) with its three
/// horizons, at `w`×`h`, and whether this call generated it.
fn survey_scene(cli: &Cli, size: [u64; 3], w: u32, h: u32) -> Result<(Scene, bool)> {
    let dir = cli
        .dir
        .join(format!("survey-{}x{}x{}", size[0], size[1], size[2]));
    let spec = SyntheticSpec {
        dir: dir.clone(),
        size,
        seed: 11,
    };
    let generated = strata_coordinator::demo::ensure_synthetic(&spec, &ProgressBar::hidden())?;
    let scene_path = dir.join("scene.toml");
    let text = std::fs::read_to_string(&scene_path).context("survey scene")?;
    let mut scene = Scene::parse(&scene_path, &text)?;
    scene.render.width = w;
    scene.render.height = h;
    scene.render.cache_mb = 1024;
    // The atlas (the GPU-side pool, host memory on the CPU) must hold the view's cut; the
    // 1 GiB cache is what streams.
    scene.render.atlas_mb = 4096;
    scene.volumes[0].opacity = 0.25;
    Ok((scene, generated))
}

fn cpu_vs_gpu(cli: &Cli) -> Result<()> {
    use strata_common::scene::{Backend, GpuFilter};
    let store = bonsai_store(cli)?;
    let ss = [
        cli.backends_survey_size[0],
        cli.backends_survey_size[1],
        cli.backends_survey_size[2],
    ];
    println!("## Engine backends on the same frame: bonsai (ParaView's setup) and the synthetic survey {}×{}×{} f32 with three horizons", ss[0], ss[1], ss[2]);
    println!();
    println!("| scene | size | backend | cold batch | rounds | uploaded MiB | frame (median) | samples | hits | samples/s | feedback bytes/frame | max diff vs CPU | speed-up |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    let mut outlier_notes = Vec::new();
    for name in ["bonsai", "survey"] {
        for (w, h) in [(1920u32, 1080u32), (3840, 2160)] {
            let mut cpu_row: Option<(f64, Vec<Rgba>)> = None;
            for (backend, filter) in [
                (Backend::Cpu, GpuFilter::Exact),
                (Backend::Gpu, GpuFilter::Exact),
                (Backend::Gpu, GpuFilter::Hardware),
            ] {
                let mut scene = match name {
                    "bonsai" => bonsai_scene(&store, w, h),
                    _ => survey_scene(cli, ss, w, h)?.0,
                };
                scene.render.backend = backend;
                scene.render.gpu_filter = filter;
                let mut e = match Engine::new(&scene) {
                    Ok(e) => e,
                    Err(err) => {
                        println!("| {name} | {w}×{h} | {backend:?} | skipped: {err:#} ||||||||||");
                        continue;
                    }
                };
                let view = e.view(w, h)?;
                let region = e.scene_region();
                let t = Instant::now();
                let b = e.render_batch(&view, &region)?;
                let cold = t.elapsed().as_secs_f64();
                let mut times = Vec::new();
                let mut last = None;
                for _ in 0..cli.frames.max(1) {
                    let f = e.render_frame(&view, &region)?;
                    times.push(f.seconds);
                    last = Some(f);
                }
                let med = strata_common::stats::median(&times);
                let f = last.unwrap();
                let img = f.image.to_full();
                let (diff, speed) = match &cpu_row {
                    Some((cpu_t, cpu_img)) => {
                        outlier_notes.push(format!(
                            "{name} {w}×{h} {}: {}",
                            b.backend,
                            outliers(&img, cpu_img, w, 1e-3)
                        ));
                        (
                            format!(
                                "{:.2e} (RMSE {:.2e})",
                                rmse(&img, cpu_img).1,
                                rmse(&img, cpu_img).0
                            ),
                            format!("{:.2}×", cpu_t / med),
                        )
                    }
                    None => ("–".into(), "1×".into()),
                };
                println!(
                    "| {name} | {w}×{h} | {} | {:.3} s | {} | {:.1} | {:.1} ms | {} | {} | {:.0} M/s | {} | {diff} | {speed} |",
                    b.backend,
                    cold,
                    b.rounds,
                    b.uploaded_bytes as f64 / (1 << 20) as f64,
                    med * 1e3,
                    f.stats.samples,
                    f.stats.hits,
                    f.stats.samples as f64 / med / 1e6,
                    f.gpu.feedback_bytes,
                );
                if backend == Backend::Cpu {
                    cpu_row = Some((med, img));
                }
            }
        }
    }
    println!();
    // Where the GPU image differs from the CPU image (GPU value first, then the CPU's;
    // x, y from the top left).
    for n in outlier_notes {
        println!("* {n}");
    }
    println!();
    Ok(())
}

fn survey(cli: &Cli) -> Result<()> {
    let size = [cli.survey_size[0], cli.survey_size[1], cli.survey_size[2]];
    let t = Instant::now();
    let (scene, generated) = survey_scene(cli, size, 1920, 1080)?;
    let gen_s = t.elapsed().as_secs_f64();
    let bytes: u64 = size.iter().product::<u64>() * 4;
    println!(
        "## Synthetic survey {}×{}×{} f32 ({:.2} GiB level 0) + 3 horizons, 1920×1080, 1 GiB cache{}",
        size[0],
        size[1],
        size[2],
        bytes as f64 / (1u64 << 30) as f64,
        if generated {
            format!(" (generated in {gen_s:.0} s)")
        } else {
            String::new()
        }
    );
    println!();
    let mut e = Engine::new(&scene)?;
    let view = e.view(1920, 1080)?;
    let region = e.scene_region();
    let t = Instant::now();
    let b = e.render_batch(&view, &region)?;
    let total = t.elapsed().as_secs_f64();
    let cs = e.cache_stats();
    println!("| rounds | outcome | batch time | cast time | load time | pages read | MiB read | cache hit rate | last frame | samples | samples/s | peak RSS |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    println!(
        "| {} | {:?} | {:.2} s | {:.2} s | {:.2} s | {} | {:.0} | {:.1}% | {:.0} ms | {} | {:.0} M/s | {} |",
        b.rounds,
        b.outcome,
        total,
        b.cast_seconds,
        b.load_seconds,
        cs.pages_read,
        cs.bytes_read as f64 / (1 << 20) as f64,
        100.0 * cs.hits as f64 / (cs.hits + cs.misses).max(1) as f64,
        b.last_seconds * 1e3,
        b.last.samples,
        b.last.samples as f64 / b.last_seconds / 1e6,
        // The process's high-water mark: the survey's own only when nothing ran before it.
        if cli.only_survey {
            format!("{:.0} MiB", peak_rss_mib())
        } else {
            "– (see --only-survey)".to_string()
        }
    );
    println!();
    println!(
        "per round (requested / missing / uploaded): {}",
        b.reports
            .iter()
            .map(|r| format!("{}/{}/{}", r.requested, r.missing, r.uploaded))
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(())
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    // As the worker and coordinator binaries do: freed frame buffers stay in the heap.
    strata_worker::node::retain_freed_memory();
    std::fs::create_dir_all(&cli.dir)?;
    println!(
        "bench-render, {} threads",
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    println!();
    if cli.only_caster {
        caster::run(&CasterArgs {
            bonsai: bonsai_store(&cli)?,
            frames: cli.frames,
            threads: cli.threads.clone(),
            case: cli.case.clone(),
            path_filter: cli.path_filter.clone(),
        })?;
        println!("peak RSS {:.0} MiB", peak_rss_mib());
        return Ok(());
    }
    if cli.only_effects {
        effects::run(&effects::EffectsArgs {
            bonsai: bonsai_store(&cli)?,
            raw: bonsai_path(&cli),
            dir: cli.dir.clone(),
            frames: cli.frames,
            size: [cli.effects_size[0], cli.effects_size[1]],
            cpu: !cli.effects_gpu_only,
            gpu: !cli.no_gpu && !strata_worker::gpu::list_adapters().is_empty(),
            threads: cli.effects_threads,
            only: cli.effects_only.clone(),
        })?;
        println!("peak RSS {:.0} MiB", peak_rss_mib());
        return Ok(());
    }
    if !cli.only_survey && !cli.only_backends {
        bonsai(&cli)?;
    }
    if !cli.no_gpu && !cli.only_survey {
        cpu_vs_gpu(&cli)?;
    }
    if !cli.no_survey && !cli.only_backends {
        survey(&cli)?;
    }
    println!("peak RSS {:.0} MiB", peak_rss_mib());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outliers_name_the_worst_pixel() {
        let a = vec![[0.0f32; 4]; 6];
        let mut b = a.clone();
        assert_eq!(outliers(&a, &b, 3, 1e-3), "0 px > 1e-3");
        b[4][2] = 0.5;
        b[1][0] = 0.01;
        assert_eq!(
            outliers(&a, &b, 3, 1e-3),
            "2 px > 1e-3; worst at (1, 1): (0.0000, 0.0000, 0.0000, 0.0000) against \
             (0.0000, 0.0000, 0.5000, 0.0000)"
        );
    }
}
