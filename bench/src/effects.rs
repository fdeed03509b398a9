//! `bench-render --only-effects`: what each effect costs a frame that does not use it, and
//! what it costs when used (issue 12, part 3).
//!
//! For each effect, a scene without it renders on the code specialised to its effects
//! (twice, in two engines: their difference is the noise floor of the run), on the same
//! code with that one effect compiled in as well, and on the general path (every effect
//! compiled in); then the scene with the effect renders on its own specialised code.
//! All engines converge first and then render their frames interleaved, in rounds whose
//! order alternates (A B C D, then D C B A), so drift of the machine hits every column
//! alike. Times are the process's CPU time per frame (`CLOCK_PROCESS_CPUTIME_ID`): on a
//! shared virtual machine, time stolen by other guests inflates wall time but not CPU
//! time. A cost is the median over rounds of the ratio of two configurations' times in the
//! same round. The images of the scene without the effect must be identical bit for bit on
//! all three paths.

use anyhow::{bail, Result};
use std::path::PathBuf;
use strata_common::effects::EffectSet;
use strata_common::image::Rgba;
use strata_common::scene::{Backend, Scene};
use strata_worker::engine::Engine;

/// What `--only-effects` runs on.
pub(crate) struct EffectsArgs {
    /// The bonsai store.
    pub(crate) bonsai: PathBuf,
    /// The bonsai raw file (a shifted copy is built from it).
    pub(crate) raw: PathBuf,
    /// Scratch folder (a second, shifted bonsai store goes here).
    pub(crate) dir: PathBuf,
    /// Timed frames per configuration.
    pub(crate) frames: usize,
    /// Frame size.
    pub(crate) size: [u32; 2],
    /// The CPU caster's tables.
    pub(crate) cpu: bool,
    /// The GPU caster's table (any adapter, lavapipe included).
    pub(crate) gpu: bool,
    /// Threads of the CPU caster's pool (1: no scheduling noise between rayon threads).
    pub(crate) threads: usize,
    /// Only these effects' rows (by name; empty: all).
    pub(crate) only: Vec<String>,
}

/// One effect's comparison.
struct Case {
    /// The effect.
    effect: EffectSet,
    /// The scene without it, in words.
    without_name: &'static str,
    without: Scene,
    /// The same scene with it.
    with: Scene,
}

struct Run {
    median: f64,
    /// CPU seconds per round.
    times: Vec<f64>,
    samples: u64,
    image: Vec<Rgba>,
    variant: String,
}

/// CPU seconds of this process so far, all threads (the scheduler's own accounting,
/// nanosecond resolution, unlike `getrusage`'s ticks).
fn cpu_seconds() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes into the struct we own.
    unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// Median over rounds of `b / a − 1`, in per cent.
fn paired_cost(a: &Run, b: &Run) -> f64 {
    let r: Vec<f64> = a.times.iter().zip(&b.times).map(|(x, y)| y / x).collect();
    100.0 * (strata_common::stats::median(&r) - 1.0)
}

/// Converges every engine, then renders `frames` rounds of one frame each, the order
/// reversed every other round.
fn interleaved(configs: &[(&Scene, EffectSet)], frames: usize) -> Result<Vec<Run>> {
    let mut engines = Vec::new();
    for (scene, extra) in configs {
        let mut e = Engine::new(scene)?;
        e.extra_effects = *extra;
        let view = e.view(scene.render.width, scene.render.height)?;
        let region = e.scene_region();
        e.render_batch(&view, &region)?;
        engines.push((e, view, region));
    }
    let mut times = vec![Vec::new(); engines.len()];
    let mut last = Vec::new();
    let n = engines.len();
    for round in 0..frames.max(1) + 1 {
        last.clear();
        last.resize_with(n, || None);
        for k in 0..n {
            let i = if round % 2 == 0 { k } else { n - 1 - k };
            let (e, view, region) = &mut engines[i];
            let c0 = cpu_seconds();
            let f = e.render_frame(view, region)?;
            // The first round warms caches and builds GPU pipelines.
            if round > 0 {
                times[i].push(cpu_seconds() - c0);
            }
            last[i] = Some(f);
        }
    }
    Ok(times
        .into_iter()
        .zip(last)
        .map(|(t, f)| {
            let f = f.expect("every engine rendered");
            Run {
                median: strata_common::stats::median(&t),
                times: t,
                samples: f.stats.samples,
                image: f.image.to_full(),
                variant: f.variant_name,
            }
        })
        .collect())
}

fn identical(a: &[Rgba], b: &[Rgba]) -> bool {
    a.len() == b.len()
        && a.iter()
            .zip(b)
            .all(|(p, q)| p.iter().zip(q).all(|(x, y)| x.to_bits() == y.to_bits()))
}

fn sized(mut s: Scene, size: [u32; 2], backend: Backend) -> Scene {
    s.render.width = size[0];
    s.render.height = size[1];
    s.render.backend = backend;
    s
}

/// The cases: bonsai-based for the volume effects, the demo survey for the surfaces.
fn cases(args: &EffectsArgs, scalar: bool) -> Result<Vec<Case>> {
    let mut out = Vec::new();
    let bonsai = {
        let mut s = crate::bonsai_scene(&args.bonsai, args.size[0], args.size[1]);
        s.render.simd = !scalar;
        s
    };
    let mut shaded = bonsai.clone();
    shaded.render.volume_shading = true;
    out.push(Case {
        effect: EffectSet::SHADING,
        without_name: "bonsai",
        without: bonsai.clone(),
        with: shaded,
    });
    let mut pre = bonsai.clone();
    pre.render.preintegrated = true;
    out.push(Case {
        effect: EffectSet::PREINTEGRATED,
        without_name: "bonsai",
        without: bonsai.clone(),
        with: pre,
    });
    let mut two = bonsai.clone();
    let mut second = two.volumes[0].clone();
    second.store = shifted_bonsai(args)?;
    two.volumes.push(second);
    out.push(Case {
        effect: EffectSet::VOLUMES,
        without_name: "bonsai",
        without: bonsai,
        with: two,
    });
    // The demo: the cube at opacity 0.06 with its slices and horizons.
    let demo = crate::caster::demo(0.06)?;
    let mut demo = sized(demo, args.size, Backend::Cpu);
    demo.render.simd = !scalar;
    let mut cube = demo.clone();
    cube.horizons.clear();
    cube.volumes[0].slices.clear();
    let mut with_h = cube.clone();
    with_h.horizons = demo.horizons.clone();
    out.push(Case {
        effect: EffectSet::HORIZONS,
        without_name: "demo cube",
        without: cube.clone(),
        with: with_h.clone(),
    });
    let mut unlit = with_h.clone();
    unlit.render.lighting = false;
    out.push(Case {
        effect: EffectSet::LIGHTING,
        without_name: "demo cube + unlit horizons",
        without: unlit,
        with: with_h,
    });
    let mut with_s = cube.clone();
    with_s.volumes[0].slices = demo.volumes[0].slices.clone();
    out.push(Case {
        effect: EffectSet::SLICES,
        without_name: "demo cube",
        without: cube,
        with: with_s,
    });
    let mut surfaces = demo.clone();
    surfaces.volumes[0].opacity = 0.0;
    out.push(Case {
        effect: EffectSet::VOLUME,
        without_name: "demo slices + horizons",
        without: surfaces,
        with: demo,
    });
    Ok(out)
}

/// The bonsai moved by half its size along x and y (a second volume that overlaps the first
/// in a quarter of its footprint).
fn shifted_bonsai(args: &EffectsArgs) -> Result<PathBuf> {
    crate::bonsai_store_at(
        &args.raw,
        &args.dir,
        "bonsai-shifted",
        strata_common::geo::Affine3::scale_offset([1.0; 3], [128.0, 128.0, 0.0]),
    )
}

fn table(args: &EffectsArgs, backend: Backend, scalar: bool) -> Result<()> {
    let what = match (backend, scalar) {
        // lavapipe runs the shader on the CPU, so CPU time is the shader's time; on a
        // hardware GPU it would be the driver's.
        (Backend::Gpu, _) => "GPU caster (CPU time: on lavapipe, the shader's)",
        (_, false) => "CPU caster, SIMD packets where they apply (the default)",
        (_, true) => "CPU caster, scalar march (`render.simd = false`)",
    };
    println!(
        "### {what}, {}×{}, {} thread(s), CPU time, medians of {} interleaved rounds",
        args.size[0],
        args.size[1],
        rayon::current_num_threads(),
        args.frames
    );
    println!();
    println!("| effect | scene without it | specialised | noise (same code again) | effect compiled in | unused cost | general path | general cost | compiled in ≤ 2 % | scene with it | cost when used | samples/s (specialised) |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for case in cases(args, scalar)? {
        if !args.only.is_empty() && !args.only.contains(&case.effect.to_string()) {
            continue;
        }
        let without = sized(case.without.clone(), args.size, backend);
        let with = sized(case.with.clone(), args.size, backend);
        let runs = interleaved(
            &[
                (&without, EffectSet::NONE),
                (&without, case.effect),
                (&without, EffectSet::ALL),
                (&with, EffectSet::NONE),
                (&without, EffectSet::NONE),
            ],
            args.frames,
        )?;
        let [a, b, g, w, a2] = [&runs[0], &runs[1], &runs[2], &runs[3], &runs[4]];
        if !identical(&a.image, &b.image)
            || !identical(&a.image, &g.image)
            || !identical(&a.image, &a2.image)
        {
            bail!(
                "{}: the code paths gave different images ({} / {} / {})",
                case.effect,
                a.variant,
                b.variant,
                g.variant
            );
        }
        let unused = paired_cost(a, b);
        println!(
            "| {} | {} (`{}`) | {:.1} ms | {:+.1} % | {:.1} ms | {:+.1} % | {:.1} ms | {:+.1} % | {} | {:.1} ms | {:+.0} % | {:.0} M/s |",
            case.effect,
            case.without_name,
            a.variant,
            a.median * 1e3,
            paired_cost(a, a2),
            b.median * 1e3,
            unused,
            g.median * 1e3,
            paired_cost(a, g),
            if unused <= 2.0 { "met" } else { "**not met**" },
            w.median * 1e3,
            paired_cost(a, w),
            a.samples as f64 / a.median / 1e6,
        );
    }
    println!();
    Ok(())
}

/// Runs the comparison.
pub(crate) fn run(args: &EffectsArgs) -> Result<()> {
    println!("## What effects cost (issue 12, part 3)");
    println!();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads)
        .build()?;
    pool.install(|| -> Result<()> {
        if args.cpu {
            table(args, Backend::Cpu, false)?;
            table(args, Backend::Cpu, true)?;
        }
        if args.gpu {
            table(args, Backend::Gpu, false)?;
        }
        Ok(())
    })
}
