//! `coordinator study accuracy`: what accuracy costs in time, for one scene.
//!
//! Renders a reference (CPU, step/16, no early termination, level 0 only, fixed step,
//! colours accumulated in f64; the same accumulated in f32 is compared with it and noted),
//! then each knob alone and in pairs, each point converged once and then timed over
//! `frames` frames with everything resident, interleaved with frames of the defaults (a
//! ratio measured side by side). Every point records the median frame time, the
//! samples, and its RMSE, largest error (premultiplied linear RGBA) and 1 − SSIM (the
//! displayed image) against the reference. The report (`report.md`), the table
//! (`points.csv`) and one plot per knob (`<knob>.png`, `.svg`) go to the output folder,
//! with the Pareto front of all points drawn and the defaults checked against it.

pub mod metrics;
pub mod pareto;
pub mod plot;
mod points;
mod report;

use crate::builder::{build_store, BuildOptions};
use crate::overrides::load_scene;
use crate::source::MemorySource;
use anyhow::{bail, Context, Result};
use indicatif::ProgressBar;
use metrics::Errors;
use std::path::{Path, PathBuf};
use strata_common::filter::CoarsenFilter;
use strata_common::image::Rgba;
use strata_common::scene::Scene;
use strata_common::store::PageStore;
use strata_worker::engine::Engine;
use tracing::info;

pub use points::{variants, Variant, Where};

/// What to study.
#[derive(Clone, Debug)]
pub struct StudyOptions {
    /// Scene TOML.
    pub scene: PathBuf,
    /// Output folder (created).
    pub out: PathBuf,
    /// `--size WxH`.
    pub size: Option<(u32, u32)>,
    /// `--set` overrides applied to every point (and the reference).
    pub sets: Vec<String>,
    /// Timed frames per point (median reported).
    pub frames: usize,
    /// Workers of the distributed points (0: no distributed points).
    pub workers: usize,
    /// Also the GPU points (any adapter, software Vulkan included).
    pub gpu: bool,
}

/// One measured point.
#[derive(Clone, Debug)]
pub struct Point {
    /// The knob it varies ("defaults" for the scene as given, "reference").
    pub knob: String,
    /// Its value(s), short.
    pub label: String,
    /// The `--set` overrides that reproduce it (plus the store swaps in `label`).
    pub sets: Vec<String>,
    /// Median seconds per converged frame (distributed: the slowest worker's cast plus
    /// the compositing).
    pub seconds: f64,
    /// Trilinear samples of the frame.
    pub samples: u64,
    /// Against the reference.
    pub errors: Errors,
    /// Backend (and adapter) that rendered.
    pub backend: String,
    /// Anything the reader should know (did not converge, ...).
    pub note: String,
    /// It rendered the defaults' image bit for bit from as many samples (the same work):
    /// its time cannot put the defaults off the Pareto front.
    pub same_work: bool,
    /// Its time is a ratio to the defaults' measured side by side (every in-process point);
    /// a point timed alone (the distributed ones) is shown but left off the Pareto front
    /// and the verdict.
    pub side_by_side: bool,
}

/// An image and how it was made.
pub(crate) struct Measured {
    pub(crate) seconds: f64,
    pub(crate) samples: u64,
    pub(crate) image: Vec<Rgba>,
    pub(crate) backend: String,
    pub(crate) note: String,
    /// Its time over the defaults', timed side by side (interleaved frames); `None` for a
    /// point timed alone (distributed points).
    pub(crate) ratio: Option<f64>,
}

/// A converged in-process engine whose frames can be timed again, everything resident.
pub(crate) struct Resident {
    engine: Engine,
    view: strata_common::camera::View,
    region: strata_common::kd::Region,
    /// Seconds of every frame timed so far.
    times: Vec<f64>,
    /// Its image and samples (of its first frame after converging).
    pub(crate) measured: Measured,
}

impl Resident {
    /// Converges once, then renders one frame for the image (not timed).
    pub(crate) fn converge(scene: &Scene) -> Result<Resident> {
        let mut engine = Engine::new(scene)?;
        let view = engine.view(scene.render.width, scene.render.height)?;
        let region = engine.scene_region();
        let b = engine.render_batch(&view, &region)?;
        let note = match b.outcome.as_str() {
            "converged" => String::new(),
            o => format!("{o} after {} rounds", b.rounds),
        };
        let f = engine.render_frame(&view, &region)?;
        Ok(Resident {
            engine,
            view,
            region,
            times: Vec::new(),
            measured: Measured {
                seconds: f.seconds,
                samples: f.stats.samples,
                image: f.image.to_full(),
                backend: b.backend,
                note,
                ratio: None,
            },
        })
    }

    /// Times one more frame.
    fn time(&mut self) -> Result<f64> {
        let f = self.engine.render_frame(&self.view, &self.region)?;
        self.times.push(f.seconds);
        Ok(f.seconds)
    }

    /// Median of every frame timed so far.
    pub(crate) fn median(&self) -> f64 {
        median(&self.times)
    }
}

fn median(v: &[f64]) -> f64 {
    strata_common::stats::median(v)
}

/// Times `frames` frames of `point` interleaved with as many of `defaults` (the machine's
/// speed drifts by tens of percent over seconds: only a ratio measured side by side is
/// firm) and returns the point, its `seconds` its own median and its `ratio` the median
/// of its frame times over the defaults' frame times of the same pairs.
pub(crate) fn side_by_side(
    mut point: Resident,
    defaults: &mut Resident,
    frames: usize,
) -> Result<Measured> {
    let mut ratios = Vec::new();
    for i in 0..frames.max(1) {
        // Alternate which goes first, so neither always follows the other.
        let (p, d) = if i % 2 == 0 {
            let p = point.time()?;
            (p, defaults.time()?)
        } else {
            let d = defaults.time()?;
            (point.time()?, d)
        };
        ratios.push(p / d);
    }
    let mut m = point.measured;
    m.seconds = median(&point.times);
    m.ratio = Some(median(&ratios));
    Ok(m)
}

/// Converges once, then times `frames` frames (median) with everything resident.
pub(crate) fn measure_in_process(scene: &Scene, frames: usize) -> Result<Measured> {
    let mut r = Resident::converge(scene)?;
    for _ in 0..frames.max(1) {
        r.time()?;
    }
    let mut m = r.measured;
    m.seconds = median(&r.times);
    Ok(m)
}

/// Bytes of the level-0 pages of the stores (what a level-0-only frame may need
/// resident; the atlases hold f32 samples).
fn level0_bytes<'a>(stores: impl IntoIterator<Item = &'a std::path::Path>) -> Result<u64> {
    let mut total = 0u64;
    for path in stores {
        let s = PageStore::open(path).with_context(|| format!("opening {}", path.display()))?;
        let p = s.pyramid();
        total += p.level(0).page_count() * p.page_samples() as u64 * 4;
    }
    Ok(total)
}

/// The reference's overrides: CPU, step/16, no early termination, fixed step, a τ so small
/// that every sample (and every horizon tile) is taken from level 0, and atlases and a
/// cache that hold level 0 of the volumes and of the horizons (a horizon atlas of the
/// default size left a large horizon's reference at coarser levels than the points it
/// judged).
fn reference_sets(scene: &Scene) -> Result<Vec<String>> {
    let mib = level0_bytes(scene.volumes.iter().map(|v| v.store.as_path()))?.div_ceil(1 << 20) + 64;
    let hmib =
        level0_bytes(scene.horizons.iter().map(|h| h.store.as_path()))?.div_ceil(1 << 20) + 16;
    let r = &scene.render;
    let cache = mib + hmib;
    Ok(vec![
        "render.backend=cpu".into(),
        format!("render.step={}", r.step / 16.0),
        "render.early_termination=1.0".into(),
        "render.adaptive_step=false".into(),
        "render.tau=1e-6".into(),
        format!("render.atlas_mb={}", r.atlas_mb.max(mib + mib / 4)),
        format!(
            "render.horizon_atlas_mb={}",
            r.horizon_atlas_mb.max(hmib + hmib / 4)
        ),
        format!("render.cache_mb={}", r.cache_mb.max(cache + cache / 4)),
        format!("render.max_rounds={}", r.max_rounds.max(64)),
        "render.f64_accumulation=true".into(),
    ])
}

/// Level 0 of a volume store, in memory (the study's stores are small; larger ones are
/// refused rather than read for minutes).
fn level0(store: &PageStore) -> Result<MemorySource> {
    let p = store.pyramid();
    let dims = p.level(0).dims;
    let n = dims.iter().product::<u64>();
    if n > (1 << 29) {
        bail!(
            "{}: level 0 holds {n} samples; the coarsening-filter knob rebuilds stores of at most 2^29",
            store.path().display()
        );
    }
    let mut data = vec![f32::NAN; n as usize];
    let pd = p.page_dims().map(|d| d as i64);
    let mut page = vec![0f32; p.page_samples()];
    let bricks = p.level(0).bricks;
    for bz in 0..bricks[2] {
        for by in 0..bricks[1] {
            for bx in 0..bricks[0] {
                let b = [bx, by, bz];
                let id = p.id(0, b);
                if store.entry(id).is_none() {
                    continue;
                }
                store.read_page_into(id, &mut page)?;
                let org = p.page_origin(b);
                let cr = p.core_range(0, b);
                for z in cr[2].0..cr[2].1 {
                    for y in cr[1].0..cr[1].1 {
                        for x in cr[0].0..cr[0].1 {
                            let l = [x as i64 - org[0], y as i64 - org[1], z as i64 - org[2]];
                            let src = ((l[2] * pd[1] + l[1]) * pd[0] + l[0]) as usize;
                            data[((z * dims[1] + y) * dims[0] + x) as usize] = page[src];
                        }
                    }
                }
            }
        }
    }
    Ok(MemorySource { dims, data })
}

/// Rebuilds a volume store with another coarsening filter (same level 0, pages, border,
/// compression, transform and survey grid).
pub fn rebuild_with_filter(src: &Path, filter: CoarsenFilter, out: &Path) -> Result<()> {
    let store = PageStore::open(src).with_context(|| format!("opening {}", src.display()))?;
    let h = store.header().clone();
    if h.no_data.is_some() {
        bail!(
            "{}: stores with a no-data value are not rebuilt (the sentinel would be lost)",
            src.display()
        );
    }
    let grid = level0(&store)?;
    let mut o = BuildOptions::volume(&h.name, h.sample_type);
    o.page_size = h.page_size;
    o.border = h.border;
    o.filter = filter;
    o.compression = h.compression;
    o.transform = h.transform;
    o.units = h.units;
    o.survey = h.survey;
    o.source = format!("{} rebuilt with the {filter:?} filter", h.source);
    build_store(&grid, out, &o, &ProgressBar::hidden())?;
    Ok(())
}

/// Runs the study and writes its outputs; returns the points (reference first, then the
/// defaults).
pub fn run(opts: &StudyOptions, progress: &ProgressBar) -> Result<Vec<Point>> {
    std::fs::create_dir_all(&opts.out)
        .with_context(|| format!("creating {}", opts.out.display()))?;
    let base = load_scene(&opts.scene, &opts.sets, opts.size)?;
    if base.wall.is_some() {
        bail!(
            "{}: the study renders one image of render.width × render.height, not a [wall]'s \
             tiles; study a copy of the scene without its [wall] table",
            opts.scene.display()
        );
    }
    if let Some(spec) = &base.synthetic {
        crate::demo::ensure_synthetic(spec, progress)?;
    }
    let (w, h) = (base.render.width as usize, base.render.height as usize);
    let bg = base.render.background.map(|c| c as f32);
    let scratch = tempfile::Builder::new()
        .prefix(".study-")
        .tempdir_in(&opts.out)
        .with_context(|| format!("scratch folder in {}", opts.out.display()))?;
    let vars = variants(&base, opts);
    progress.set_length(vars.len() as u64 + 2);
    progress.set_message("reference");

    // Opens every store to size the atlases: once.
    let reference_overrides = reference_sets(&base)?;
    let mut ref_sets = opts.sets.clone();
    ref_sets.extend(reference_overrides.iter().cloned());
    let ref_scene = load_scene(&opts.scene, &ref_sets, opts.size)?;
    let r = measure_in_process(&ref_scene, 1).context("the reference render")?;
    // Every point is judged against it: a reference that stopped short (an atlas too small,
    // the round limit) is not the most accurate image.
    if !r.note.is_empty() {
        bail!(
            "the reference render did not converge ({}): its overrides are {}",
            r.note,
            ref_sets.join(" ")
        );
    }
    info!(
        seconds = r.seconds,
        samples = r.samples,
        "reference rendered"
    );
    // What f64 accumulation buys: the same render accumulated in f32, as the caster
    // accumulates every other point.
    let mut f32_sets = ref_sets.clone();
    f32_sets.push("render.f64_accumulation=false".into());
    let r32 = measure_in_process(&load_scene(&opts.scene, &f32_sets, opts.size)?, 1)
        .context("the reference's settings accumulated in f32")?;
    let e32 = metrics::compare(&r32.image, &r.image, w, h, bg);
    info!(
        rmse = e32.rmse,
        max = e32.max,
        seconds = r32.seconds,
        "the reference accumulated in f32"
    );
    let mut ref_note = r.note.clone();
    if !ref_note.is_empty() {
        ref_note.push_str("; ");
    }
    ref_note.push_str(&format!(
        "accumulated in f32 instead: RMSE {:.1e}, max {:.1e}, {:.0} ms",
        e32.rmse,
        e32.max,
        r32.seconds * 1e3
    ));
    progress.inc(1);
    let zero = Errors {
        rmse: 0.0,
        max: 0.0,
        dssim: 0.0,
    };
    let mut out = vec![Point {
        knob: "reference".into(),
        label: "reference".into(),
        sets: reference_overrides,
        seconds: r.seconds,
        samples: r.samples,
        errors: zero,
        backend: r.backend.clone(),
        note: ref_note,
        same_work: false,
        side_by_side: false,
    }];
    let reference = r.image;

    progress.set_message("defaults");
    // The defaults stay resident for the whole study: every in-process point's frames are
    // timed interleaved with theirs, and its time reported as the ratio so measured times
    // the defaults' median over the study. (Timed one after the other, identical settings
    // differed by up to 60 % between points, and the verdict flipped with the noise.)
    let mut defaults = Resident::converge(&base).context("the defaults")?;
    for _ in 0..opts.frames.max(1) {
        defaults.time().context("the defaults")?;
    }
    let d = &defaults.measured;
    out.push(Point {
        knob: "defaults".into(),
        label: "defaults".into(),
        sets: Vec::new(),
        seconds: f64::NAN,
        samples: d.samples,
        errors: metrics::compare(&d.image, &reference, w, h, bg),
        backend: d.backend.clone(),
        note: d.note.clone(),
        same_work: true,
        side_by_side: true,
    });
    let mut ratios: Vec<Option<f64>> = vec![None, Some(1.0)];
    progress.inc(1);

    for v in &vars {
        progress.set_message(format!("{} {}", v.knob, v.label));
        let m = points::measure(v, opts, scratch.path(), &mut defaults);
        progress.inc(1);
        let m = match m {
            Ok(m) => m,
            Err(e) => {
                info!(knob = v.knob, label = %v.label, "skipped: {e:#}");
                out.push(Point {
                    knob: v.knob.into(),
                    label: v.label.clone(),
                    sets: v.sets.clone(),
                    seconds: f64::NAN,
                    samples: 0,
                    errors: Errors {
                        rmse: f64::NAN,
                        max: f64::NAN,
                        dssim: f64::NAN,
                    },
                    backend: String::new(),
                    note: format!("skipped: {e:#}"),
                    same_work: false,
                    side_by_side: false,
                });
                ratios.push(None);
                continue;
            }
        };
        if m.image.len() != w * h {
            bail!(
                "{} {}: image of {} pixels, expected {w}x{h}",
                v.knob,
                v.label,
                m.image.len()
            );
        }
        // The defaults' image, bit for bit, from as many samples: the same work, so a
        // difference in time is noise and cannot put the defaults off the front.
        let same_work = m.samples == defaults.measured.samples
            && m.image.len() == defaults.measured.image.len()
            && m.image
                .iter()
                .zip(&defaults.measured.image)
                .all(|(a, b)| (0..4).all(|c| a[c].to_bits() == b[c].to_bits()));
        let mut note = m.note;
        if same_work {
            if !note.is_empty() {
                note.push_str("; ");
            }
            note.push_str("the defaults' image and samples");
        }
        out.push(Point {
            knob: v.knob.into(),
            label: v.label.clone(),
            sets: v.sets.clone(),
            seconds: m.seconds,
            samples: m.samples,
            errors: metrics::compare(&m.image, &reference, w, h, bg),
            backend: m.backend,
            note,
            same_work,
            side_by_side: m.ratio.is_some(),
        });
        ratios.push(m.ratio);
    }
    // Side-by-side ratios become times at the defaults' median over the whole study.
    let base_s = defaults.median();
    for (p, r) in out.iter_mut().zip(&ratios) {
        if let Some(r) = r {
            p.seconds = r * base_s;
        } else if p.seconds.is_finite() && p.knob != "reference" {
            if !p.note.is_empty() {
                p.note.push_str("; ");
            }
            p.note
                .push_str("timed alone, not side by side: left off the front and the verdict");
        }
    }
    report::write(opts, &base, &out)?;
    Ok(out)
}
