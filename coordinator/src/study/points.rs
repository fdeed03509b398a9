//! The knobs of the accuracy study and how each point is rendered.

use super::{rebuild_with_filter, side_by_side, Measured, Resident, StudyOptions};
use crate::overrides::load_scene;
use crate::render::{render_distributed, RenderOptions};
use anyhow::{Context, Result};
use indicatif::ProgressBar;
use std::path::Path;
use strata_common::filter::CoarsenFilter;
use strata_common::scene::Scene;
use strata_common::store::PageStore;

/// Where a point renders.
#[derive(Clone, Debug, PartialEq)]
pub enum Where {
    /// In this process through the worker engine.
    InProcess,
    /// Over this many local worker processes (QUIC compositing).
    Distributed(usize),
    /// In this process, with every volume store rebuilt with this coarsening filter.
    Filter(CoarsenFilter),
}

/// One point to measure.
#[derive(Clone, Debug)]
pub struct Variant {
    /// Knob (plot and table name).
    pub knob: &'static str,
    /// Value(s), short.
    pub label: String,
    /// Overrides on top of the study's own.
    pub sets: Vec<String>,
    /// Where it renders.
    pub how: Where,
}

fn v(knob: &'static str, label: String, sets: Vec<String>) -> Variant {
    Variant {
        knob,
        label,
        sets,
        how: Where::InProcess,
    }
}

/// The study's points for a scene: each knob alone over a range around the scene's value,
/// then pairs. Values equal to the scene's own are left out (the defaults point is that).
pub fn variants(scene: &Scene, opts: &StudyOptions) -> Vec<Variant> {
    let r = &scene.render;
    let mut out = Vec::new();
    for f in [0.25, 0.5, 2.0, 4.0] {
        let s = r.step * f;
        out.push(v(
            "step",
            format!("step {s}"),
            vec![format!("render.step={s}")],
        ));
    }
    for t in [0.25, 0.5, 2.0, 4.0, 8.0] {
        let t = r.tau * t;
        out.push(v("tau", format!("τ {t}"), vec![format!("render.tau={t}")]));
    }
    for e in [0.9, 0.95, 0.98, 0.995, 0.999, 1.0] {
        if e != r.early_termination {
            out.push(v(
                "early-termination",
                format!("ERT {e}"),
                vec![format!("render.early_termination={e}")],
            ));
        }
    }
    let a = !r.adaptive_step;
    out.push(v(
        "adaptive-step",
        format!("adaptive {a}"),
        vec![format!("render.adaptive_step={a}")],
    ));
    // The filter the scene's first volume was built with is the defaults point.
    let current = scene
        .volumes
        .first()
        .and_then(|l| PageStore::open(&l.store).ok())
        .map(|s| s.header().filter);
    for f in [
        CoarsenFilter::Mean,
        CoarsenFilter::SignedRms,
        CoarsenFilter::MaxAbs,
    ] {
        if !scene.volumes.is_empty() && Some(f) != current {
            out.push(Variant {
                knob: "coarsening-filter",
                label: format!("{f:?}"),
                sets: Vec::new(),
                how: Where::Filter(f),
            });
        }
    }
    if opts.workers >= 2 {
        for wire in ["f32", "f16"] {
            out.push(Variant {
                knob: "wire-precision",
                label: format!("{} workers, {wire}", opts.workers),
                sets: vec![format!("composite.wire={wire}")],
                how: Where::Distributed(opts.workers),
            });
        }
    }
    out.push(v(
        "backend",
        "cpu".into(),
        vec!["render.backend=cpu".into()],
    ));
    if opts.gpu {
        out.push(v(
            "backend",
            "gpu".into(),
            vec![
                "render.backend=gpu".into(),
                "render.gpu_filter=exact".into(),
            ],
        ));
        out.push(v(
            "gpu-filter",
            "gpu hardware".into(),
            vec![
                "render.backend=gpu".into(),
                "render.gpu_filter=hardware".into(),
            ],
        ));
    }
    for p in [true, false] {
        if p != r.preintegrated {
            out.push(v(
                "preintegrated",
                format!("preintegrated {p}"),
                vec![format!("render.preintegrated={p}")],
            ));
        }
    }
    // Pre-integration with coarser steps; on the GPU also at the scene's own step.
    let mut pre = vec![(false, 2.0), (false, 4.0)];
    if opts.gpu {
        pre.extend([(true, 1.0), (true, 2.0)]);
    }
    for (gpu, f) in pre {
        let s = r.step * f;
        let mut sets = vec![
            format!("render.step={s}"),
            "render.preintegrated=true".into(),
        ];
        if gpu {
            sets.extend([
                "render.backend=gpu".into(),
                "render.gpu_filter=exact".into(),
            ]);
        }
        let on = if gpu { "gpu, " } else { "" };
        out.push(v(
            "step+preintegrated",
            format!("{on}step {s}, preint."),
            sets,
        ));
    }
    // Pairs: the two knobs that trade the most, together.
    for (f, t) in [(0.5, 0.5), (2.0, 2.0), (0.5, 2.0), (2.0, 0.5)] {
        let (s, t) = (r.step * f, r.tau * t);
        out.push(v(
            "step+tau",
            format!("step {s}, τ {t}"),
            vec![format!("render.step={s}"), format!("render.tau={t}")],
        ));
    }
    for (f, e) in [(0.5, 1.0), (2.0, 0.95), (2.0, 1.0)] {
        let s = r.step * f;
        out.push(v(
            "step+early-termination",
            format!("step {s}, ERT {e}"),
            vec![
                format!("render.step={s}"),
                format!("render.early_termination={e}"),
            ],
        ));
    }
    out
}

/// Renders one point.
/// Measures one point: in process, its frames interleaved with the `defaults`' (see
/// [`side_by_side`]); distributed, one batch frame timed alone.
pub(crate) fn measure(
    v: &Variant,
    opts: &StudyOptions,
    scratch: &Path,
    defaults: &mut Resident,
) -> Result<Measured> {
    let mut sets = opts.sets.clone();
    sets.extend(v.sets.iter().cloned());
    match &v.how {
        Where::InProcess => {
            let scene = load_scene(&opts.scene, &sets, opts.size)?;
            side_by_side(Resident::converge(&scene)?, defaults, opts.frames)
        }
        Where::Filter(f) => {
            let mut scene = load_scene(&opts.scene, &sets, opts.size)?;
            for (i, l) in scene.volumes.iter_mut().enumerate() {
                let out = scratch.join(format!("volume{i}-{f:?}.strata"));
                if !out.exists() {
                    rebuild_with_filter(&l.store, *f, &out)?;
                }
                l.store = out;
            }
            side_by_side(Resident::converge(&scene)?, defaults, opts.frames)
        }
        Where::Distributed(n) => {
            let png = scratch.join("distributed.png");
            let exr = scratch.join("distributed.exr");
            let ro = RenderOptions {
                scene: opts.scene.clone(),
                output: png,
                exr: Some(exr.clone()),
                sets,
                size: opts.size,
                workers: Some(*n),
                ..RenderOptions::default()
            };
            let s = render_distributed(&ro, &ProgressBar::hidden())?;
            let image = read_exr(&exr)?;
            Ok(Measured {
                // The time of every cast `samples` counts (the occlusion first pass too,
                // which the compositing time leaves out) and the compositing.
                seconds: s.last_frame_seconds + s.first_pass_seconds + s.composite_seconds,
                samples: s.samples,
                image,
                backend: format!("{} ({} workers)", s.backend, s.workers),
                note: format!(
                    "one batch frame; {} exchanged, {}",
                    s.exchange_bytes,
                    s.algorithm.unwrap_or_default()
                ),
                ratio: None,
            })
        }
    }
}

fn read_exr(path: &Path) -> Result<Vec<[f32; 4]>> {
    let image = exr::prelude::read_first_rgba_layer_from_file(
        path,
        |res, _| (res.width(), vec![[0f32; 4]; res.width() * res.height()]),
        |(w, px): &mut (usize, Vec<[f32; 4]>), pos, (r, g, b, a): (f32, f32, f32, f32)| {
            px[pos.y() * *w + pos.x()] = [r, g, b, a];
        },
    )
    .with_context(|| format!("reading {}", path.display()))?;
    Ok(image.layer_data.channel_data.pixels.1)
}
