//! `coordinator render`: a scene to an image.
//!
//! Distributed rendering (the default) splits the scene over worker processes
//! ([`crate::cluster`]); each renders its k-d subtree and the partial images are
//! composited by exchange among the workers. In-process rendering runs the worker engine
//! in this process over the whole scene as one region, in batch mode (frame → feedback →
//! load until converged). It is the reference that distributed rendering must match.
//!
//! `--orbit N` renders a sequence of N frames around the scene's target, and `--path FILE`
//! the frames of a camera path, with the same workers (or the same in-process engine)
//! throughout, so stores stay open and resident pages stay resident between frames; each
//! frame's output path is numbered by its `%05d`. `--frames A..B` renders only part of a
//! sequence (the outputs keep the sequence's frame numbers).

use crate::cluster::{Cluster, ClusterOptions};
use crate::{demo, image_out, overrides};
use anyhow::{Context, Result};
use indicatif::ProgressBar;
use std::path::{Path, PathBuf};
use std::time::Instant;
use strata_common::scene::{Camera, Scene, MAX_IMAGE_SIDE};
use strata_common::wire::{CompositeChoice, FrameSource, WorkerFrameStats};
use strata_worker::engine::Engine;
use tracing::{info, warn};

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
    /// `--path FILE`: the frames of a camera path.
    pub path: Option<PathBuf>,
    /// `--frames A..B`: only sequence frames `A..B` (end exclusive).
    pub frames: Option<(u32, u32)>,
    /// `--mp4` follows the sequence: it encodes the `-o` frames, so they must be written.
    pub mp4: bool,
}

/// `--mp4 FILE` after a sequence: the frames `--frames` asked for (all of them when
/// resumed), at the camera path's fps or 24 for an orbit.
pub fn write_mp4(opts: &RenderOptions, out: &Path) -> Result<crate::sequence::Mp4> {
    let (fps, n) = match (&opts.path, opts.orbit) {
        (Some(p), _) => {
            let path = load_path(p)?;
            (path.fps, path.frame_count())
        }
        (None, Some(n)) => (24.0, n),
        (None, None) => anyhow::bail!("--mp4 needs a sequence (--orbit N or --path FILE)"),
    };
    // Only these frames: others of the sequence may lie beside them (another part of an
    // array job), and ffmpeg would read on until a number is missing.
    let (first, end) = opts.frames.unwrap_or((0, n));
    let end = end.min(n);
    crate::sequence::encode_mp4(&opts.output, first, end.saturating_sub(first), fps, out)
}

/// Parses `--frames`: `A..B` (B excluded) or `A..=B` (B included).
pub fn parse_frames(s: &str) -> Result<(u32, u32)> {
    let err = || {
        anyhow::anyhow!(
            "--frames {s:?}: expected A..B (frames A to B−1) or A..=B, e.g. --frames 0..100"
        )
    };
    let (a, b, inclusive) = match s.split_once("..=") {
        Some((a, b)) => (a, b, true),
        None => {
            let (a, b) = s.split_once("..").ok_or_else(err)?;
            (a, b, false)
        }
    };
    let a: u32 = a.trim().parse().map_err(|_| err())?;
    let b: u32 = b.trim().parse().map_err(|_| err())?;
    let b = if inclusive {
        b.checked_add(1).ok_or_else(err)?
    } else {
        b
    };
    anyhow::ensure!(a < b, "--frames {s:?} holds no frame");
    Ok((a, b))
}

/// Reads a camera path: JSON by the `.json` extension, TOML otherwise; errors name the file
/// and, for syntax, line and column.
fn load_path(p: &Path) -> Result<strata_common::camera_path::CameraPath> {
    use strata_common::camera_path::CameraPath;
    let text = std::fs::read_to_string(p)
        .with_context(|| format!("reading camera path {}", p.display()))?;
    let path = if p
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("json"))
    {
        let c: CameraPath =
            serde_json::from_str(&text).with_context(|| format!("camera path {}", p.display()))?;
        c.check()
            .with_context(|| format!("camera path {}", p.display()))?;
        c
    } else {
        CameraPath::from_toml(&text).with_context(|| format!("camera path {}", p.display()))?
    };
    Ok(path)
}

/// Whether frame outputs already exist complete (a PNG and, when one is asked for, an EXR,
/// each of the right size and whole), so a resumed job skips the frame. Outputs are written
/// atomically, so a killed job leaves no half-written file under these names; but an EXR
/// of an earlier run at another size, or a damaged one, is not complete.
fn complete(scene: &Scene, f: &FramePlan, width: u32, height: u32) -> bool {
    if let Some(wall) = &scene.wall {
        // Every tile's files, and the preview when one is asked for.
        let g = wall.geometry();
        let (pw, ph) = g.plane_size();
        let tiles = image_out::tile_files(&g, &f.png, f.exr.as_deref());
        return tiles.iter().all(|t| {
            png_complete(&t.png, g.tile_w, g.tile_h)
                && t.exr
                    .as_ref()
                    .is_none_or(|e| exr_complete(e, g.tile_w, g.tile_h))
        }) && (!wall.preview || png_complete(&f.png, pw, ph));
    }
    png_complete(&f.png, width, height)
        && f.exr
            .as_ref()
            .is_none_or(|e| exr_complete(e, width, height))
}

/// Whether `png` is a PNG of `width × height` that decodes, row by row (a wall's preview
/// may be gigabytes as one buffer).
fn png_complete(png: &Path, width: u32, height: u32) -> bool {
    (|| -> Option<()> {
        let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(png).ok()?));
        let mut reader = decoder.read_info().ok()?;
        let info = reader.info();
        if (info.width, info.height) != (width, height) {
            return None;
        }
        let mut rows = 0u32;
        while reader.next_row().ok()?.is_some() {
            rows += 1;
        }
        (rows == height).then_some(())
    })()
    .is_some()
}

/// Whether `exr` is an EXR of one `width × height` layer whose every chunk is there (read
/// chunk by chunk, not decompressed).
fn exr_complete(exr: &Path, width: u32, height: u32) -> bool {
    (|| -> Option<()> {
        let file = std::io::BufReader::new(std::fs::File::open(exr).ok()?);
        let reader = ::exr::block::read(file, true).ok()?;
        match reader.headers() {
            [h] if h.layer_size.0 == width as usize && h.layer_size.1 == height as usize => {}
            _ => return None,
        }
        for chunk in reader.all_chunks(true).ok()? {
            chunk.ok()?;
        }
        Some(())
    })()
    .is_some()
}

/// One frame of a sequence: its number, camera and output paths.
#[derive(Clone)]
struct FramePlan {
    index: u32,
    camera: Camera,
    png: PathBuf,
    exr: Option<PathBuf>,
}

/// The file that names frame `f` in the summary: its PNG, or, for a wall without its
/// preview mosaic (only tiles are written), its first tile.
fn frame_output(scene: &Scene, f: &FramePlan) -> String {
    match &scene.wall {
        Some(wall) if !wall.preview => display(&strata_common::wall::tile_path(&f.png, 0, 0)),
        _ => display(&f.png),
    }
}

/// The most frames one `--orbit` may ask for.
const MAX_FRAMES: u32 = 1_000_000;

/// The checks of a run's sequence options: [`check_frames`], and that `--mp4` has frames
/// to encode (a wall writes its `-o` frames only with its preview; this reads the scene).
/// `coordinator render` makes them before it creates the frames' folder, so a refused
/// command leaves nothing behind.
pub fn check_sequence(opts: &RenderOptions) -> Result<()> {
    if opts.mp4 {
        let scene = overrides::load_scene(&opts.scene, &opts.sets, opts.size)?;
        anyhow::ensure!(
            scene.wall.as_ref().is_none_or(|w| w.preview),
            "--mp4 encodes the -o frames, which a wall writes only with wall.preview = true \
             (without it each tile is its own file)"
        );
    }
    check_frames(opts)
}

/// The checks of a run's sequence options that need no scene: `--orbit`'s count, the
/// camera path (read and checked), `--frames` against the sequence, numbered outputs.
/// [`plan_frames`] makes them again.
fn check_frames(opts: &RenderOptions) -> Result<()> {
    let (n, what) = match (&opts.path, opts.orbit) {
        (Some(p), _) => (
            load_path(p)?.frame_count(),
            format!("--path {}", p.display()),
        ),
        (None, Some(n)) => {
            anyhow::ensure!(
                (1..=MAX_FRAMES).contains(&n),
                "--orbit {n}: the frame count must lie in 1..={MAX_FRAMES}"
            );
            (n, format!("--orbit {n}"))
        }
        (None, None) => {
            anyhow::ensure!(
                opts.frames.is_none(),
                "--frames needs a sequence (--orbit N or --path FILE)"
            );
            return Ok(());
        }
    };
    for p in std::iter::once(&opts.output).chain(&opts.exr) {
        anyhow::ensure!(
            crate::sequence::is_numbered(p)?,
            "{what}: the output {} needs a frame-number pattern, e.g. frames/frame_%05d.png",
            p.display()
        );
    }
    let (a, b) = opts.frames.unwrap_or((0, n));
    anyhow::ensure!(
        a < n,
        "--frames {a}..{b}: the sequence has frames 0..{n} ({what})"
    );
    Ok(())
}

/// The run's frames: the camera alone, `--orbit N` frames around it, or a camera path's
/// frames, with numbered paths, cut to `--frames`. Also returns how many frames of the range
/// were skipped because their outputs are complete already.
fn plan_frames(
    opts: &RenderOptions,
    scene: &Scene,
    camera: &Camera,
    width: u32,
    height: u32,
) -> Result<(Vec<FramePlan>, usize)> {
    check_frames(opts)?;
    let (n, what, at): (u32, String, Box<dyn Fn(u32) -> Camera>) = match (&opts.path, opts.orbit) {
        (Some(p), _) => {
            let path =
                load_path(p)?.with_default_up(strata_common::camera::world_up(&scene.render));
            let n = path.frame_count();
            (
                n,
                format!("--path {}", p.display()),
                Box::new(move |i| path.frame(i)),
            )
        }
        (None, Some(n)) => {
            let c = camera.clone();
            (
                n,
                format!("--orbit {n}"),
                Box::new(move |i| strata_common::camera::orbit(&c, n, i)),
            )
        }
        (None, None) => {
            let one = FramePlan {
                index: 0,
                camera: camera.clone(),
                png: opts.output.clone(),
                exr: opts.exr.clone(),
            };
            return Ok((vec![one], 0));
        }
    };
    let (a, b) = opts.frames.unwrap_or((0, n));
    if b > n {
        warn!("--frames {a}..{b}: the sequence has frames 0..{n} ({what}); rendering {a}..{n}");
    }
    let mut plan = Vec::new();
    let mut skipped = 0;
    for i in a..b.min(n) {
        let camera = at(i);
        // Every frame's view is checked before any is rendered: a path whose interpolation
        // passes the eye through the target fails here, naming the frame, not mid-run.
        frame_view(scene, &camera, &scene.render, width.max(1), height.max(1))
            .with_context(|| format!("{what}: frame {i}"))?;
        let f = FramePlan {
            index: i,
            camera,
            png: crate::sequence::numbered(&opts.output, i)?,
            exr: opts
                .exr
                .as_ref()
                .map(|e| crate::sequence::numbered(e, i))
                .transpose()?,
        };
        if complete(scene, &f, width, height) {
            skipped += 1;
        } else {
            plan.push((i, f));
        }
    }
    Ok((plan.into_iter().map(|(_, f)| f).collect(), skipped))
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
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct FrameSummary {
    /// Frame number.
    pub frame: u32,
    /// The PNG written (a wall frame without its preview mosaic: its first tile, column 0
    /// and row 0).
    pub output: String,
    /// Wall time of the frame: its render and composite, and whatever wait remained for the
    /// previous frame's files (a frame's files are written while the next frame renders, so
    /// its own write shows in the next frame's time, and the last frame's in the run's).
    pub seconds: f64,
    /// Feedback rounds (the most of any worker).
    pub rounds: u32,
    /// "converged", "round-limit" or "atlas-full" (the worst of any worker).
    pub outcome: String,
    /// Trilinear samples of the frame's final round (all workers; distributed, with their
    /// occlusion re-casts and first pass, as [`RenderSummary::samples`]).
    pub samples: u64,
    /// Seconds of the final round's cast ([`RenderSummary::last_frame_seconds`] of this
    /// frame: distributed, the slowest worker's).
    pub last_round_seconds: f64,
    /// Seconds of each feedback round's cast (distributed: the slowest worker's in each
    /// round, its leaves summed; see `WorkerFrameStats::round_cast_s`).
    pub round_cast_seconds: Vec<f64>,
    /// Seconds of each round's loads and atlas update, as `round_cast_seconds`.
    pub round_load_seconds: Vec<f64>,
    /// Seconds casting, all rounds (distributed: summed over the workers, their occlusion
    /// first pass and re-cast included).
    pub cast_seconds: f64,
    /// Seconds loading pages and updating the atlas (distributed: summed over the workers).
    pub load_seconds: f64,
    /// Exchange + gather (distributed: `FrameResult::composite_s`; 0 in-process).
    pub composite_seconds: f64,
    /// Bytes the workers sent each other (0 in-process).
    pub exchange_bytes: u64,
    /// Bytes received with the final pieces, as [`RenderSummary::gather_bytes`] (0
    /// in-process).
    pub gather_bytes: u64,
    /// Cross-worker occlusion (`cluster.occlusion`): screen blocks the workers left uncast,
    /// predicted hidden by the workers in front of them (summed over the workers; 0
    /// in-process).
    pub occluded_blocks: u64,
    /// Blocks cast again because the frame's own front transmittance did not confirm the
    /// prediction (left out, or stopped at a threshold the frame does not allow; summed
    /// over the workers).
    pub fixup_blocks: u64,
    /// Seconds the coordinator spent on the frame's occlusion maps: decoding the workers'
    /// coverage, folding it in visibility order, encoding and sending each position's map
    /// (`FrameResult::occlusion_s`; 0 in-process and without `cluster.occlusion`).
    pub occlusion_map_seconds: f64,
    /// The effects the frame drew (`volume+horizons+lighting`; workers whose leaves differ
    /// are joined by `; `).
    pub effects: String,
    /// The code path that drew them, e.g. `specialised [volume+horizons] simd`.
    pub variant: String,
}

/// The largest value of each round over the workers' per-round lists.
fn slowest_per_round<'a>(lists: impl Iterator<Item = &'a [f64]>) -> Vec<f64> {
    let mut out: Vec<f64> = Vec::new();
    for l in lists {
        if out.len() < l.len() {
            out.resize(l.len(), 0.0);
        }
        for (o, &v) in out.iter_mut().zip(l) {
            *o = o.max(v);
        }
    }
    out
}

/// Joins the distinct non-empty strings, in order of first appearance, by `; `.
fn distinct<'a>(items: impl Iterator<Item = &'a str>) -> String {
    let mut out: Vec<&str> = Vec::new();
    for list in items {
        for s in list.split("; ").filter(|s| !s.is_empty()) {
            if !out.contains(&s) {
                out.push(s);
            }
        }
    }
    out.join("; ")
}

/// Logs a frame's effects and code path.
fn log_frame(s: &FrameSummary) {
    info!(
        frame = s.frame,
        seconds = format!("{:.3}", s.seconds),
        effects = %s.effects,
        variant = %s.variant,
        "frame rendered"
    );
}

/// What a render did.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct RenderSummary {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Feedback rounds.
    pub rounds: u32,
    /// "converged", "round-limit" or "atlas-full".
    pub outcome: String,
    /// Trilinear samples of the final frame: in-process, its final round's; distributed,
    /// every worker's final render round, occlusion re-casts and occlusion first pass (the
    /// work the image took, as `WorkerFrameStats::samples` counts it).
    pub samples: u64,
    /// Seconds of the final round's cast of the last frame (distributed: the slowest
    /// worker's, all its leaves, its occlusion re-cast included; with selective rounds the
    /// last full round's time scaled to the converged tiles, see `last_round_s`).
    pub last_frame_seconds: f64,
    /// Seconds of the last frame's occlusion first pass, its low-resolution map exchange
    /// included (the slowest worker's; 0 in-process, without occlusion and on frames that
    /// predict from the previous one): with `last_frame_seconds`, the time of the casts
    /// `samples` counts. (The wait for the full frame's front map is not in it: that is
    /// the front workers' render, which `last_frame_seconds` holds already.)
    pub first_pass_seconds: f64,
    /// Seconds casting over all rounds and frames (distributed: summed over the workers;
    /// an attempt abandoned when a worker was lost is not in it: its time is in the frame's
    /// `seconds` and the loss's `recovery_s`).
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
    /// The effects of the last frame (see [`FrameSummary::effects`]).
    pub effects: String,
    /// The code path of the last frame (see [`FrameSummary::variant`]).
    pub variant: String,
    /// Bytes written to the GPU (pages, tables) over the batch (in-process GPU runs; 0 in
    /// distributed runs, whose workers do not report it).
    pub gpu_uploaded_bytes: u64,
    /// Feedback bytes read back from the GPU in the final frame (in-process GPU runs; 0 in
    /// distributed runs, whose workers do not report it).
    pub gpu_feedback_bytes: u64,
    /// Whether the synthetic survey was generated by this run.
    pub generated_synthetic: bool,
    /// Total wall time.
    pub seconds: f64,
    /// Of it, the seconds from asking the workers to shut down to their exit and closed
    /// connections (distributed runs; 0 in process).
    pub shutdown_seconds: f64,
    /// Worker processes that rendered the last frame (0: rendered in-process).
    pub workers: usize,
    /// Compositing algorithm (distributed runs).
    pub algorithm: Option<String>,
    /// Exchange + gather time of the last frame (distributed runs; `FrameResult::composite_s`).
    pub composite_seconds: f64,
    /// Bytes the workers sent each other in the last frame.
    pub exchange_bytes: u64,
    /// Bytes the coordinator received with the last frame's final pieces: each worker's
    /// frame header, its `FrameDone` message (its stats, page records included) and its
    /// pixels (those written into the canvas counted as the f32 pixels written). The
    /// workers' own `gather_bytes` count the pixels alone.
    pub gather_bytes: u64,
    /// Of the exchanged bytes, those that went through shared memory.
    pub exchange_shm_bytes: u64,
    /// Workers whose final piece of the last frame was written in place into the
    /// coordinator's shared canvas (workers on its host), not sent.
    pub canvas_gather: usize,
    /// How pieces travelled (distributed runs): pairs and gathers over shared memory and
    /// over QUIC (`cluster.transport`).
    pub transport: Option<crate::cluster::TransportReport>,
    /// Workers given up on during the run (their frames were re-rendered without them).
    pub lost_workers: Vec<crate::cluster::LostWorker>,
    /// Workers that joined the running sequence (cluster mode) and took load.
    pub joined_workers: Vec<crate::cluster::JoinedWorker>,
    /// Per-worker stats of each frame (distributed runs).
    #[serde(skip)]
    pub frames: Vec<Vec<WorkerFrameStats>>,
    /// Each frame of the run.
    #[serde(skip)]
    pub sequence: Vec<FrameSummary>,
    /// Frames rendered.
    pub frame_count: usize,
    /// Frames of the range skipped because their outputs were complete (resume).
    pub skipped: usize,
    /// Re-splits of the k-d tree between frames (distributed sequences).
    #[serde(skip)]
    pub rebalances: Vec<crate::cluster::Rebalance>,
    /// A powerwall's `[columns, rows]` of tiles (each frame wrote one file per tile).
    pub wall: Option<[u32; 2]>,
    /// Whether the wall's preview mosaic was written to the output path.
    pub wall_preview: bool,
}

impl RenderSummary {
    /// The summary of a run with nothing left to render (every frame complete already).
    fn nothing(width: u32, height: u32, skipped: usize, generated: bool, t0: Instant) -> Self {
        RenderSummary {
            width,
            height,
            outcome: "converged".into(),
            backend: "none".into(),
            generated_synthetic: generated,
            seconds: t0.elapsed().as_secs_f64(),
            skipped,
            ..RenderSummary::default()
        }
    }

    /// `--stats` output: one JSON object per line: per frame (`"kind": "frame"`), per re-split (`"kind": "rebalance"`), per worker
    /// and frame (`"kind": "worker"`), then the summary (`"kind": "summary"`).
    pub fn json_lines(&self) -> Result<String> {
        let mut out = String::new();
        for f in &self.sequence {
            let mut v = serde_json::to_value(f)?;
            v["kind"] = "frame".into();
            out += &serde_json::to_string(&v)?;
            out.push('\n');
        }
        for r in &self.rebalances {
            let mut v = serde_json::to_value(r)?;
            v["kind"] = "rebalance".into();
            out += &serde_json::to_string(&v)?;
            out.push('\n');
        }
        for (i, workers) in self.frames.iter().enumerate() {
            // The sequence's frame number, as the frame lines carry it (with `--frames` or a
            // resume, not the count of frames this run rendered).
            let frame = self.sequence.get(i).map_or(i as u64, |f| f.frame as u64);
            for w in workers {
                let mut v = serde_json::to_value(w)?;
                // The per-page shares fed the re-split (and are dropped after it).
                if let Some(o) = v.as_object_mut() {
                    o.remove("page_work");
                }
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
        (1..=MAX_IMAGE_SIDE).contains(&w) && (1..=MAX_IMAGE_SIDE).contains(&h),
        "{}: render.width and render.height must lie in 1..={MAX_IMAGE_SIDE}, got {w}x{h}",
        opts.scene.display()
    );
    // (`Scene::parse` has checked the wall's layout.)
    if scene.wall.is_some() && opts.size.is_some() {
        warn!("--size is not used with [wall]: each tile is wall.tile_size");
    }
    Ok((scene, generated))
}

/// The image a frame renders: the scene's `render.width × height`, or a wall's stacked
/// tiles.
fn frame_size(scene: &Scene) -> (u32, u32) {
    match &scene.wall {
        Some(w) => w.geometry().stacked_size(),
        None => (scene.render.width, scene.render.height),
    }
}

/// Writes a frame's outputs from its image (`w × h`, the stacked tiles for a wall): the PNG
/// and EXR, or a wall's tile files and its preview mosaic.
fn write_outputs(scene: &Scene, f: &FramePlan, w: u32, h: u32, image: &[[f32; 4]]) -> Result<()> {
    let bg = scene.render.background.map(|c| c as f32);
    match &scene.wall {
        None => {
            image_out::write_png(&f.png, w, h, image, bg)?;
            if let Some(exr) = &f.exr {
                image_out::write_exr(exr, w, h, image)?;
            }
        }
        Some(wall) => {
            let g = wall.geometry();
            let files = image_out::tile_files(&g, &f.png, f.exr.as_deref());
            image_out::write_tiles(&g, 0, image, &files, bg)?;
            if wall.preview {
                image_out::write_preview(&g, &files, &f.png)?;
            }
        }
    }
    Ok(())
}

/// The view of a frame: the camera over `w × h` pixels, or over a wall's frustum.
fn frame_view(
    scene: &Scene,
    camera: &Camera,
    settings: &strata_common::scene::RenderSettings,
    w: u32,
    h: u32,
) -> Result<strata_common::camera::View> {
    use strata_common::camera::View;
    Ok(match &scene.wall {
        Some(wall) => View::wall(camera, settings, &wall.geometry())?,
        None => View::new(camera, settings, w, h)?,
    })
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
        lz4: c.lz4,
    };
    choice.plan(workers, 1).with_context(|| {
        format!(
            "composite.algorithm = {} with composite.k = {:?} cannot composite {workers} workers",
            serde_json::to_string(&c.algorithm).unwrap_or_default(),
            choice.k
        )
    })?;
    Ok(choice)
}

/// Renders `opts.scene` over worker processes (spawned here, or launched elsewhere when
/// `cluster.spawn = false`).
pub fn render_distributed(opts: &RenderOptions, progress: &ProgressBar) -> Result<RenderSummary> {
    let t0 = Instant::now();
    let (scene, generated) = prepare(opts, progress)?;
    let (w, h) = frame_size(&scene);
    let copts = ClusterOptions::from_scene(&scene, opts.workers)?;
    if let Some(wall) = &scene.wall {
        wall.drivers(copts.workers)
            .with_context(|| format!("{}: [wall]", opts.scene.display()))?;
    }
    let n = copts.workers;
    let choice = composite_choice(&scene, n)?;
    let camera = match &scene.camera {
        Some(c) => c.clone(),
        None => {
            let data = strata_worker::dataset::SceneData::open(&scene)?;
            strata_common::camera::default_camera(&data.bounds(), &scene.render)
        }
    };
    let (plan, skipped) = plan_frames(opts, &scene, &camera, w, h)?;
    if plan.is_empty() {
        return Ok(RenderSummary::nothing(w, h, skipped, generated, t0));
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    progress.set_message(format!("rendering on {n} workers"));
    let result = rt.block_on(async {
        let run = async {
            let mut cluster = Cluster::start(&scene, copts).await?;
            frame_progress(progress, plan.len());
            let mut done = Vec::with_capacity(plan.len());
            let mut rebalances = Vec::new();
            let mut sequence = Vec::with_capacity(plan.len());
            // A frame's files are written while the next frame renders: one write in
            // flight, waited for before the next starts (and its error reported then).
            let shared_scene = std::sync::Arc::new(scene.clone());
            let mut writing: Option<(u32, tokio::task::JoinHandle<Result<()>>)> = None;
            async fn finish(w: Option<(u32, tokio::task::JoinHandle<Result<()>>)>) -> Result<()> {
                if let Some((i, h)) = w {
                    h.await
                        .map_err(|e| anyhow::anyhow!("writing frame {i}: {e}"))?
                        .with_context(|| format!("writing frame {i}"))?;
                }
                Ok(())
            }
            for f in &plan {
                let i = f.index;
                let t = Instant::now();
                let bg = scene.render.background.map(|c| c as f32);
                let mut fr = match &scene.wall {
                    // The drivers write the tiles; the preview is assembled from them.
                    Some(wall) => {
                        let g = wall.geometry();
                        let files = image_out::tile_files(&g, &f.png, f.exr.as_deref());
                        let fr = cluster
                            .frame_wall(&f.camera, wall, &files, bg, &choice)
                            .await
                            .with_context(|| format!("frame {i}"))?;
                        if wall.preview {
                            tokio::task::block_in_place(|| {
                                image_out::write_preview(&g, &files, &f.png)
                            })?;
                        }
                        fr
                    }
                    None => {
                        let mut fr = cluster
                            .frame(&f.camera, w, h, &choice, FrameSource::Render)
                            .await
                            .with_context(|| format!("frame {i}"))?;
                        finish(writing.take()).await?;
                        let image = std::mem::replace(
                            &mut fr.image,
                            crate::cluster::FrameImage::Owned(Vec::new()),
                        );
                        let (sc, plan_f) = (shared_scene.clone(), f.clone());
                        writing = Some((
                            i,
                            tokio::task::spawn_blocking(move || {
                                write_outputs(&sc, &plan_f, w, h, &image)
                            }),
                        ));
                        fr
                    }
                };
                for j in &mut fr.joined {
                    j.frame = i as u64;
                }
                sequence.push(FrameSummary {
                    frame: i,
                    output: frame_output(&scene, f),
                    seconds: t.elapsed().as_secs_f64(),
                    rounds: fr.stats.iter().map(|s| s.render_rounds).max().unwrap_or(0),
                    outcome: worst_outcome(fr.stats.iter().map(|s| s.outcome.as_str())),
                    samples: saturating_total(fr.stats.iter().map(|s| s.samples)),
                    last_round_seconds: fr.stats.iter().map(|s| s.last_round_s).fold(0.0, f64::max),
                    round_cast_seconds: slowest_per_round(
                        fr.stats.iter().map(|s| &s.round_cast_s[..]),
                    ),
                    round_load_seconds: slowest_per_round(
                        fr.stats.iter().map(|s| &s.round_load_s[..]),
                    ),
                    cast_seconds: fr.stats.iter().map(|s| s.cast_s).sum(),
                    load_seconds: fr.stats.iter().map(|s| s.load_s).sum(),
                    composite_seconds: fr.composite_s,
                    exchange_bytes: saturating_total(fr.stats.iter().map(|s| s.bytes_sent)),
                    gather_bytes: fr.gather_bytes,
                    occluded_blocks: saturating_total(fr.stats.iter().map(|s| s.occluded_blocks)),
                    fixup_blocks: saturating_total(fr.stats.iter().map(|s| s.fixup_blocks)),
                    occlusion_map_seconds: fr.occlusion_s,
                    effects: distinct(fr.stats.iter().map(|s| s.effects.as_str())),
                    variant: distinct(fr.stats.iter().map(|s| s.variant.as_str())),
                });
                log_frame(sequence.last().expect("just pushed"));
                progress.inc(1);
                if f.index != plan.last().map_or(f.index, |l| l.index) {
                    // (On the thread that drives the run, not a runtime worker: the
                    // connections' readers and keep-alives go on while it balances.)
                    if let Some(r) = cluster.rebalance(&fr, i as u64) {
                        rebalances.push(r);
                    }
                }
                // The page records have served the re-split; a long sequence keeps only
                // the rest of each worker's stats.
                for s in &mut fr.stats {
                    s.page_work = Vec::new();
                }
                done.push(fr);
            }
            finish(writing.take()).await?;
            let transport = cluster.transport().clone();
            let t = Instant::now();
            cluster.shutdown().await;
            let shutdown_s = t.elapsed().as_secs_f64();
            anyhow::Ok((done, sequence, rebalances, transport, shutdown_s))
        };
        tokio::select! {
            r = run => r,
            _ = tokio::signal::ctrl_c() => anyhow::bail!("interrupted (Ctrl-C); workers stopped"),
        }
    });
    // Dropping the runtime kills any worker still running (kill_on_drop).
    drop(rt);
    let (mut done, sequence, rebalances, transport, shutdown_s) = result?;
    let lost_workers: Vec<crate::cluster::LostWorker> =
        done.iter().flat_map(|f| f.lost.iter().cloned()).collect();
    let joined_workers: Vec<crate::cluster::JoinedWorker> =
        done.iter().flat_map(|f| f.joined.iter().cloned()).collect();
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
        samples: saturating_total(fr.stats.iter().map(|s| s.samples)),
        // The same quantities as in-process, under the same names: the final round's cast
        // (of the slowest worker), casting and loading summed over the engines and the run's
        // frames, reads and cache lookups over the engines since they opened the scene.
        last_frame_seconds: fr.stats.iter().map(|s| s.last_round_s).fold(0.0, f64::max),
        first_pass_seconds: fr.stats.iter().map(|s| s.prepass_s).fold(0.0, f64::max),
        cast_seconds: frames.iter().flatten().map(|s| s.cast_s).sum(),
        load_seconds: frames.iter().flatten().map(|s| s.load_s).sum(),
        // Cache counters are per worker since it opened the scene: the last frame's.
        cache_hit_rate: {
            let (h, l) = fr.stats.iter().fold((0u64, 0u64), |(h, l), s| {
                (
                    h.saturating_add(s.cache_hits),
                    l.saturating_add(s.cache_lookups),
                )
            });
            h as f64 / l.max(1) as f64
        },
        pages_read: saturating_total(fr.stats.iter().map(|s| s.pages_read)),
        bytes_read: saturating_total(fr.stats.iter().map(|s| s.bytes_read)),
        backend: {
            let mut b: Vec<&str> = fr.stats.iter().map(|s| s.backend.as_str()).collect();
            b.sort_unstable();
            b.dedup();
            b.join("; ")
        },
        effects: distinct(fr.stats.iter().map(|s| s.effects.as_str())),
        variant: distinct(fr.stats.iter().map(|s| s.variant.as_str())),
        gpu_uploaded_bytes: 0,
        gpu_feedback_bytes: 0,
        generated_synthetic: generated,
        seconds: t0.elapsed().as_secs_f64(),
        shutdown_seconds: shutdown_s,
        // The last frame's, which the compositing figures beside it are of (fewer than the
        // run started with after a loss; `lost_workers` and `joined_workers` tell).
        workers: fr.stats.len(),
        algorithm: Some(format!("{:?}", choice.algorithm)),
        composite_seconds: fr.composite_s,
        exchange_bytes: saturating_total(fr.stats.iter().map(|s| s.bytes_sent)),
        gather_bytes: fr.gather_bytes,
        exchange_shm_bytes: saturating_total(fr.stats.iter().map(|s| s.shm_bytes_sent)),
        canvas_gather: fr.canvas_gather,
        lost_workers: lost_workers.clone(),
        joined_workers,
        transport: Some(transport),
        frames,
        frame_count: sequence.len(),
        sequence,
        skipped,
        rebalances,
        wall: scene.wall.as_ref().map(|w| w.tiles),
        wall_preview: scene.wall.as_ref().is_some_and(|w| w.preview),
    })
}

/// The worst of some outcomes: "converged" unless one is not.
fn worst_outcome<'a>(outcomes: impl Iterator<Item = &'a str>) -> String {
    // An atlas too small for the working set is worse than rounds that ran out (more
    // rounds would not help it); a name this build does not know (a newer worker's) is
    // worst of all.
    let rank = |o: &str| match o {
        "converged" => 0,
        "round-limit" => 1,
        "atlas-full" => 2,
        _ => 3,
    };
    outcomes
        .fold("converged", |a, b| if rank(b) > rank(a) { b } else { a })
        .to_string()
}

/// Renders `opts.scene` in this process.
pub fn render_in_process(opts: &RenderOptions, progress: &ProgressBar) -> Result<RenderSummary> {
    let t0 = Instant::now();
    let (scene, generated) = prepare(opts, progress)?;
    let (w, h) = frame_size(&scene);
    let mut engine =
        Engine::new(&scene).with_context(|| format!("scene {}", opts.scene.display()))?;
    let region = engine.scene_region();
    let (plan, skipped) = plan_frames(opts, &scene, &engine.camera().clone(), w, h)?;
    if plan.is_empty() {
        return Ok(RenderSummary::nothing(w, h, skipped, generated, t0));
    }
    progress.set_message("rendering");
    frame_progress(progress, plan.len());
    let (mut cast_seconds, mut load_seconds) = (0.0, 0.0);
    let mut sequence = Vec::with_capacity(plan.len());
    let mut last = None;
    // A frame's files are written on a thread while the next frame renders: one write in
    // flight, waited for before the next starts (and its error reported then).
    std::thread::scope(|threads| -> Result<()> {
        type Writing<'s> = Option<(u32, std::thread::ScopedJoinHandle<'s, Result<()>>)>;
        let finish = |w: Writing<'_>| -> Result<()> {
            if let Some((i, h)) = w {
                h.join()
                    .map_err(|_| anyhow::anyhow!("writing frame {i}: the writer panicked"))?
                    .with_context(|| format!("writing frame {i}"))?;
            }
            Ok(())
        };
        let mut writing: Writing<'_> = None;
        for f in &plan {
            let i = f.index;
            let t = Instant::now();
            let view = frame_view(&scene, &f.camera, &engine.settings, w, h)?;
            let result = engine
                .render_batch(&view, &region)
                .with_context(|| format!("frame {i}"))?;
            let full = result.image.to_full();
            finish(writing.take())?;
            let sc = &scene;
            writing = Some((i, threads.spawn(move || write_outputs(sc, f, w, h, &full))));
            cast_seconds += result.cast_seconds;
            load_seconds += result.load_seconds;
            sequence.push(FrameSummary {
                frame: i,
                output: frame_output(&scene, f),
                seconds: t.elapsed().as_secs_f64(),
                rounds: result.rounds,
                outcome: result.outcome.clone().as_str().into(),
                samples: result.last.samples,
                last_round_seconds: result.last_seconds,
                round_cast_seconds: result.round_cast_seconds.clone(),
                round_load_seconds: result.round_load_seconds.clone(),
                cast_seconds: result.cast_seconds,
                load_seconds: result.load_seconds,
                composite_seconds: 0.0,
                exchange_bytes: 0,
                gather_bytes: 0,
                occluded_blocks: 0,
                fixup_blocks: 0,
                occlusion_map_seconds: 0.0,
                effects: result.variant.effects.to_string(),
                variant: result.variant_name.clone(),
            });
            log_frame(sequence.last().expect("just pushed"));
            progress.inc(1);
            last = Some(result);
        }
        finish(writing.take())
    })?;
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
        first_pass_seconds: 0.0,
        cast_seconds,
        load_seconds,
        cache_hit_rate: cs.hits as f64 / lookups as f64,
        pages_read: cs.pages_read,
        bytes_read: cs.bytes_read,
        backend: result.backend.clone(),
        effects: result.variant.effects.to_string(),
        variant: result.variant_name.clone(),
        gpu_uploaded_bytes: result.uploaded_bytes,
        gpu_feedback_bytes: result.last_gpu.feedback_bytes,
        generated_synthetic: generated,
        seconds: t0.elapsed().as_secs_f64(),
        frame_count: sequence.len(),
        sequence,
        skipped,
        wall: scene.wall.as_ref().map(|w| w.tiles),
        wall_preview: scene.wall.as_ref().is_some_and(|w| w.preview),
        ..RenderSummary::default()
    })
}

/// Path helper for messages.
pub fn display(p: &Path) -> String {
    p.display().to_string()
}

/// The sum of counters the workers reported, saturating: a worker's numbers come over the
/// network and may be anything.
fn saturating_total(counts: impl Iterator<Item = u64>) -> u64 {
    counts.fold(0, u64::saturating_add)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The frame's outcome is its workers' worst, whatever their order (the last one not
    /// converged had been taken).
    #[test]
    fn the_worst_outcome_is_taken_in_any_order() {
        let w = |v: &[&str]| worst_outcome(v.iter().copied());
        assert_eq!(w(&["converged", "converged"]), "converged");
        assert_eq!(w(&["atlas-full", "round-limit"]), "atlas-full");
        assert_eq!(w(&["round-limit", "atlas-full", "converged"]), "atlas-full");
        assert_eq!(w(&["round-limit", "converged"]), "round-limit");
        assert_eq!(w(&[]), "converged");
    }

    /// The worker lines of `--stats` carry the sequence's frame numbers, as the frame lines
    /// do (with `--frames 10..12` they had counted 0, 1).
    #[test]
    fn worker_lines_carry_the_sequence_frame_number() {
        let frame = |n: u32| FrameSummary {
            frame: n,
            output: format!("f_{n}.png"),
            seconds: 0.0,
            rounds: 1,
            outcome: "converged".into(),
            ..Default::default()
        };
        let worker = |rank: u32| WorkerFrameStats {
            rank,
            ..Default::default()
        };
        let s = RenderSummary {
            sequence: vec![frame(10), frame(11)],
            frames: vec![vec![worker(0), worker(1)], vec![worker(0), worker(1)]],
            ..Default::default()
        };
        let lines = s.json_lines().unwrap();
        let workers: Vec<serde_json::Value> = lines
            .lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
            .filter(|v| v["kind"] == "worker")
            .collect();
        let frames: Vec<u64> = workers
            .iter()
            .map(|v| v["frame"].as_u64().unwrap())
            .collect();
        assert_eq!(frames, [10, 10, 11, 11]);
    }
}
