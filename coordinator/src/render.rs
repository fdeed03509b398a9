//! `coordinator render`: a scene to an image.
//!
//! Distributed rendering (the default) splits the scene over worker processes
//! ([`crate::cluster`]); each renders its k-d subtree and the partial images are
//! composited by exchange among the workers. In-process rendering runs the worker engine
//! in this process over the whole scene as one region, in batch mode (frame → feedback →
//! load until converged). It is the reference that distributed rendering must match.
//!
//! `--orbit N` renders a sequence of N frames around the scene's target with the same
//! workers (or the same in-process engine) throughout, so stores stay open and resident pages
//! stay resident between frames; each frame's output path is numbered by its `%05d`.

use crate::cluster::{Cluster, ClusterOptions};
use crate::{demo, image_out, overrides};
use anyhow::{Context, Result};
use indicatif::ProgressBar;
use std::path::{Path, PathBuf};
use std::time::Instant;
use strata_common::scene::{Camera, Scene};
use strata_common::wire::{CompositeChoice, FrameSource, WorkerFrameStats};
use strata_worker::engine::Engine;
use tracing::info;

/// What to render and where to put it.
#[derive(Clone, Debug, Default)]
pub struct RenderOptions {
    /// Scene TOML.
    pub scene: PathBuf,
    /// PNG output (8-bit sRGB).
    pub output: PathBuf,
    /// Optional float RGBA EXR output.
    pub exr: Option<PathBuf>,
    /// `key=value` overrides.
    pub sets: Vec<String>,
    /// `--size WxH`.
    pub size: Option<(u32, u32)>,
    /// `--workers N` (None: the scene's `cluster.workers`).
    pub workers: Option<usize>,
    /// `--orbit N`: N frames on a circle around the scene camera's target.
    pub orbit: Option<u32>,
}

/// One frame of a sequence: its camera and output paths.
struct FramePlan {
    camera: Camera,
    png: PathBuf,
    exr: Option<PathBuf>,
}

/// The most frames one `--orbit` may ask for.
const MAX_FRAMES: u32 = 1_000_000;

/// The run's frames: the camera alone, or `--orbit N` frames around it with numbered paths.
fn plan_frames(opts: &RenderOptions, camera: &Camera) -> Result<Vec<FramePlan>> {
    let Some(n) = opts.orbit else {
        return Ok(vec![FramePlan {
            camera: camera.clone(),
            png: opts.output.clone(),
            exr: opts.exr.clone(),
        }]);
    };
    anyhow::ensure!(
        (1..=MAX_FRAMES).contains(&n),
        "--orbit {n}: the frame count must lie in 1..={MAX_FRAMES}"
    );
    for p in std::iter::once(&opts.output).chain(&opts.exr) {
        anyhow::ensure!(
            crate::sequence::is_numbered(p)?,
            "--orbit {n}: the output {} needs a frame-number pattern, e.g. frames/frame_%05d.png",
            p.display()
        );
    }
    (0..n)
        .map(|i| {
            Ok(FramePlan {
                camera: strata_common::camera::orbit(camera, n, i),
                png: crate::sequence::numbered(&opts.output, i)?,
                exr: opts
                    .exr
                    .as_ref()
                    .map(|e| crate::sequence::numbered(e, i))
                    .transpose()?,
            })
        })
        .collect()
}

/// Turns the run's progress bar into a frame counter for sequences.
fn frame_progress(progress: &ProgressBar, frames: usize) {
    if frames > 1 {
        progress.set_style(
            indicatif::ProgressStyle::with_template(
                "{msg:>14} [{elapsed_precise}] {wide_bar:.cyan/blue} {pos}/{len} frames ({per_sec}, {eta})",
            )
            .expect("template"),
        );
        progress.set_length(frames as u64);
        progress.set_position(0);
    }
}

/// One frame of a run, as `--stats` reports it (`"kind": "frame"`).
#[derive(Clone, Debug, serde::Serialize)]
pub struct FrameSummary {
    /// Frame number.
    pub frame: u32,
    /// The PNG written.
    pub output: String,
    /// Wall time of the frame (render, composite, write).
    pub seconds: f64,
    /// Feedback rounds (the most of any worker).
    pub rounds: u32,
    /// "converged", "round-limit" or "atlas-full" (the worst of any worker).
    pub outcome: String,
    /// Trilinear samples of the frame's final round (all workers).
    pub samples: u64,
}

/// What a render did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct RenderSummary {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Feedback rounds.
    pub rounds: u32,
    /// "converged", "round-limit" or "atlas-full".
    pub outcome: String,
    /// Trilinear samples of the final frame.
    pub samples: u64,
    /// Seconds of the final round's cast of the last frame (distributed: the slowest
    /// worker's, all its leaves).
    pub last_frame_seconds: f64,
    /// Seconds casting over all rounds and frames (distributed: summed over the workers).
    pub cast_seconds: f64,
    /// Seconds loading pages and updating the atlas (distributed: summed over the workers).
    pub load_seconds: f64,
    /// Cache hits / lookups.
    pub cache_hit_rate: f64,
    /// Pages read from disk.
    pub pages_read: u64,
    /// Stored bytes read from disk.
    pub bytes_read: u64,
    /// The backend(s) and adapter(s) that rendered.
    pub backend: String,
    /// Bytes written to the GPU (pages, tables) over the batch (in-process GPU runs).
    pub gpu_uploaded_bytes: u64,
    /// Feedback bytes read back from the GPU in the final frame (in-process GPU runs).
    pub gpu_feedback_bytes: u64,
    /// Whether the synthetic survey was generated by this run.
    pub generated_synthetic: bool,
    /// Total wall time.
    pub seconds: f64,
    /// Worker processes (0: rendered in-process).
    pub workers: usize,
    /// Compositing algorithm (distributed runs).
    pub algorithm: Option<String>,
    /// Exchange + gather time of the frame (distributed runs).
    pub composite_seconds: f64,
    /// Bytes the workers sent each other.
    pub exchange_bytes: u64,
    /// Bytes of the final pieces sent to the coordinator.
    pub gather_bytes: u64,
    /// Per-worker stats of each frame (distributed runs).
    #[serde(skip)]
    pub frames: Vec<Vec<WorkerFrameStats>>,
    /// Each frame of the run.
    #[serde(skip)]
    pub sequence: Vec<FrameSummary>,
    /// Frames rendered.
    pub frame_count: usize,
}

impl RenderSummary {
    /// `--stats` output: one JSON object per line: per frame (`"kind": "frame"`), per worker
    /// and frame (`"kind": "worker"`), then the summary (`"kind": "summary"`).
    pub fn json_lines(&self) -> Result<String> {
        let mut out = String::new();
        for f in &self.sequence {
            let mut v = serde_json::to_value(f)?;
            v["kind"] = "frame".into();
            out += &serde_json::to_string(&v)?;
            out.push('\n');
        }
        for (frame, workers) in self.frames.iter().enumerate() {
            for w in workers {
                let mut v = serde_json::to_value(w)?;
                v["kind"] = "worker".into();
                v["frame"] = frame.into();
                out += &serde_json::to_string(&v)?;
                out.push('\n');
            }
        }
        let mut v = serde_json::to_value(self)?;
        v["kind"] = "summary".into();
        out += &serde_json::to_string(&v)?;
        out.push('\n');
        Ok(out)
    }
}

fn prepare(opts: &RenderOptions, progress: &ProgressBar) -> Result<(Scene, bool)> {
    let scene = overrides::load_scene(&opts.scene, &opts.sets, opts.size)?;
    let generated = match &scene.synthetic {
        Some(spec) => demo::ensure_synthetic(spec, progress).with_context(|| {
            format!(
                "generating the synthetic survey into {}",
                spec.dir.display()
            )
        })?,
        None => false,
    };
    let (w, h) = (scene.render.width, scene.render.height);
    anyhow::ensure!(
        w > 0 && h > 0 && w <= 32768 && h <= 32768,
        "{}: render.width and render.height must lie in 1..=32768, got {w}x{h}",
        opts.scene.display()
    );
    Ok((scene, generated))
}

/// The composite settings of a scene as carried in frame requests (checked: a plan is
/// built once here so a bad `composite.k` fails before any worker starts).
pub fn composite_choice(scene: &Scene, workers: usize) -> Result<CompositeChoice> {
    let c = &scene.composite;
    let choice = CompositeChoice {
        algorithm: c.algorithm,
        k: c.k.to_vec(),
        interlace: c.interlace,
        format: c.wire,
    };
    let k: Vec<usize> = choice.k.iter().map(|&k| k as usize).collect();
    strata_common::composite::build_plan(
        workers,
        1,
        choice.algorithm,
        (!k.is_empty()).then_some(&k[..]),
    )
    .with_context(|| format!("composite settings {c:?} with {workers} workers"))?;
    Ok(choice)
}

/// Renders `opts.scene` over worker processes (spawned here, or launched elsewhere when
/// `cluster.spawn = false`).
pub fn render_distributed(opts: &RenderOptions, progress: &ProgressBar) -> Result<RenderSummary> {
    let t0 = Instant::now();
    let (scene, generated) = prepare(opts, progress)?;
    let (w, h) = (scene.render.width, scene.render.height);
    let copts = ClusterOptions::from_scene(&scene, opts.workers)?;
    let n = copts.workers;
    let choice = composite_choice(&scene, n)?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    progress.set_message(format!("rendering on {n} workers"));
    let result = rt.block_on(async {
        let run = async {
            let mut cluster = Cluster::start(&scene, copts).await?;
            let camera = match &scene.camera {
                Some(c) => c.clone(),
                None => {
                    let data = strata_worker::dataset::SceneData::open(&scene)?;
                    strata_common::camera::default_camera(&data.bounds(), &scene.render)
                }
            };
            let plan = plan_frames(opts, &camera)?;
            frame_progress(progress, plan.len());
            let mut done = Vec::with_capacity(plan.len());
            let mut sequence = Vec::with_capacity(plan.len());
            for (i, f) in plan.iter().enumerate() {
                let t = Instant::now();
                let fr = cluster
                    .frame(&f.camera, w, h, &choice, FrameSource::Render)
                    .await
                    .with_context(|| format!("frame {i}"))?;
                tokio::task::block_in_place(|| -> Result<()> {
                    let bg = scene.render.background.map(|c| c as f32);
                    image_out::write_png(&f.png, w, h, &fr.image, bg)?;
                    if let Some(exr) = &f.exr {
                        image_out::write_exr(exr, w, h, &fr.image)?;
                    }
                    Ok(())
                })?;
                sequence.push(FrameSummary {
                    frame: i as u32,
                    output: display(&f.png),
                    seconds: t.elapsed().as_secs_f64(),
                    rounds: fr.stats.iter().map(|s| s.render_rounds).max().unwrap_or(0),
                    outcome: worst_outcome(fr.stats.iter().map(|s| s.outcome.as_str())),
                    samples: fr.stats.iter().map(|s| s.samples).sum(),
                });
                progress.inc(1);
                done.push(fr);
            }
            cluster.shutdown().await;
            anyhow::Ok((done, sequence))
        };
        tokio::select! {
            r = run => r,
            _ = tokio::signal::ctrl_c() => anyhow::bail!("interrupted (Ctrl-C); workers stopped"),
        }
    });
    // Dropping the runtime kills any worker still running (kill_on_drop).
    drop(rt);
    let (mut done, sequence) = result?;
    let fr = done.pop().context("no frame rendered")?;
    for s in &fr.stats {
        info!(
            rank = s.rank,
            position = s.position,
            render_s = format!("{:.3}", s.render_s),
            encode_s = format!("{:.4}", s.encode_s),
            exchange_s = format!("{:.4}", s.exchange_s),
            blend_s = format!("{:.4}", s.blend_s),
            bytes_sent = s.bytes_sent,
            bytes_received = s.bytes_received,
            outcome = %s.outcome,
            backend = %s.backend,
            "worker frame stats"
        );
    }
    let mut frames: Vec<Vec<WorkerFrameStats>> = done.into_iter().map(|f| f.stats).collect();
    frames.push(fr.stats.clone());
    Ok(RenderSummary {
        width: w,
        height: h,
        rounds: fr.stats.iter().map(|s| s.render_rounds).max().unwrap_or(0),
        outcome: worst_outcome(fr.stats.iter().map(|s| s.outcome.as_str())),
        samples: fr.stats.iter().map(|s| s.samples).sum(),
        // The same quantities as in-process, under the same names: the final round's cast
        // (of the slowest worker), casting and loading summed over the engines and the run's
        // frames, reads and cache lookups over the engines since they opened the scene.
        last_frame_seconds: fr.stats.iter().map(|s| s.last_round_s).fold(0.0, f64::max),
        cast_seconds: frames.iter().flatten().map(|s| s.cast_s).sum(),
        load_seconds: frames.iter().flatten().map(|s| s.load_s).sum(),
        // Cache counters are per worker since it opened the scene: the last frame's.
        cache_hit_rate: {
            let (h, l) = fr
                .stats
                .iter()
                .fold((0, 0), |(h, l), s| (h + s.cache_hits, l + s.cache_lookups));
            h as f64 / l.max(1) as f64
        },
        pages_read: fr.stats.iter().map(|s| s.pages_read).sum(),
        bytes_read: fr.stats.iter().map(|s| s.bytes_read).sum(),
        backend: {
            let mut b: Vec<&str> = fr.stats.iter().map(|s| s.backend.as_str()).collect();
            b.sort_unstable();
            b.dedup();
            b.join("; ")
        },
        gpu_uploaded_bytes: 0,
        gpu_feedback_bytes: 0,
        generated_synthetic: generated,
        seconds: t0.elapsed().as_secs_f64(),
        workers: n,
        algorithm: Some(format!("{:?}", choice.algorithm)),
        composite_seconds: fr.composite_s,
        exchange_bytes: fr.stats.iter().map(|s| s.bytes_sent).sum(),
        gather_bytes: fr.gather_bytes,
        frames,
        frame_count: sequence.len(),
        sequence,
    })
}

/// The worst of some outcomes: "converged" unless one is not.
fn worst_outcome<'a>(outcomes: impl Iterator<Item = &'a str>) -> String {
    outcomes
        .fold("converged", |a, b| if b != "converged" { b } else { a })
        .to_string()
}

/// Renders `opts.scene` in this process.
pub fn render_in_process(opts: &RenderOptions, progress: &ProgressBar) -> Result<RenderSummary> {
    let t0 = Instant::now();
    let (scene, generated) = prepare(opts, progress)?;
    let (w, h) = (scene.render.width, scene.render.height);
    let mut engine =
        Engine::new(&scene).with_context(|| format!("scene {}", opts.scene.display()))?;
    let region = engine.scene_region();
    let plan = plan_frames(opts, &engine.camera().clone())?;
    progress.set_message("rendering");
    frame_progress(progress, plan.len());
    let bg = scene.render.background.map(|c| c as f32);
    let (mut cast_seconds, mut load_seconds) = (0.0, 0.0);
    let mut sequence = Vec::with_capacity(plan.len());
    let mut last = None;
    for (i, f) in plan.iter().enumerate() {
        let t = Instant::now();
        let view = strata_common::camera::View::new(&f.camera, &engine.settings, w, h)?;
        let result = engine
            .render_batch(&view, &region)
            .with_context(|| format!("frame {i}"))?;
        let full = result.image.to_full();
        image_out::write_png(&f.png, w, h, &full, bg)?;
        if let Some(exr) = &f.exr {
            image_out::write_exr(exr, w, h, &full)?;
        }
        cast_seconds += result.cast_seconds;
        load_seconds += result.load_seconds;
        sequence.push(FrameSummary {
            frame: i as u32,
            output: display(&f.png),
            seconds: t.elapsed().as_secs_f64(),
            rounds: result.rounds,
            outcome: result.outcome.clone().as_str().into(),
            samples: result.last.samples,
        });
        progress.inc(1);
        last = Some(result);
    }
    let result = last.context("no frame rendered")?;
    let cs = engine.cache_stats();
    let lookups = (cs.hits + cs.misses).max(1);
    Ok(RenderSummary {
        width: w,
        height: h,
        rounds: result.rounds,
        outcome: result.outcome.as_str().into(),
        samples: result.last.samples,
        last_frame_seconds: result.last_seconds,
        cast_seconds,
        load_seconds,
        cache_hit_rate: cs.hits as f64 / lookups as f64,
        pages_read: cs.pages_read,
        bytes_read: cs.bytes_read,
        backend: result.backend.clone(),
        gpu_uploaded_bytes: result.uploaded_bytes,
        gpu_feedback_bytes: result.last_gpu.feedback_bytes,
        generated_synthetic: generated,
        seconds: t0.elapsed().as_secs_f64(),
        workers: 0,
        algorithm: None,
        composite_seconds: 0.0,
        exchange_bytes: 0,
        gather_bytes: 0,
        frames: vec![],
        frame_count: sequence.len(),
        sequence,
    })
}

/// Path helper for messages.
pub fn display(p: &Path) -> String {
    p.display().to_string()
}
