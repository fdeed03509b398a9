//! The coordinator's side of a distributed render: listen, start or await the workers,
//! authenticate them, hand out the k-d decomposition, and per frame send the camera and
//! visibility order and gather the composited pieces.
//!
//! The coordinator never relays image data between workers: they exchange pieces among
//! themselves (`strata_worker::node`) and send the coordinator only their final piece.
//! Every wait is bounded: workers must connect within `cluster.connect_timeout_s`, a frame
//! must finish within `cluster.frame_timeout_s`, and a vanished worker is noticed by its
//! process exiting (local mode) or by its connection's idle timeout, whichever comes
//! first. Errors name the worker: rank, name, pid and address. With
//! `cluster.on_worker_loss = "reassign"` (the default) a lost worker is given up, the scene
//! re-split over the workers left and the frame rendered again (`Cluster::frame`). Pairs of
//! processes on one host exchange through shared memory (`cluster.transport`).

use crate::decompose;
use crate::setup_blame::{self, Answer, Verdict};
use anyhow::{anyhow, bail, Context, Result};
use rayon::prelude::*;
use std::future::IntoFuture;
use std::net::SocketAddr;
use std::os::unix::ffi::OsStringExt;
use std::path::PathBuf;
use std::process::Stdio;
use std::sync::Arc;
use std::time::{Duration, Instant};
use strata_common::camera::{screen_motion, View};
use strata_common::composite::canvas as composite_canvas;
use strata_common::composite::{assemble, Interlace, Span, SparsePiece};
use strata_common::image::Rgba;
use strata_common::kd::Decomposition;
use strata_common::occlusion::{self, BlockGrid, FrontAccumulator, Transmittance};
use strata_common::scene::{Camera, Scene, WallSettings};
use strata_common::scene::{RebalanceClock, RebalanceModel, Transport};
use strata_common::wall::TileFiles;
use strata_common::wire::{
    self, CompositeChoice, CoordMsg, FrameRequest, FrameSource, Limits, PeerInfo, Setup, WallFrame,
    WorkerFrameStats, WorkerMsg,
};
use strata_net::canvas::Canvas;
use strata_net::canvas::PIXEL_BYTES;
use strata_net::frame::{read_frame, with_timeout, write_frame, NetError};
use strata_net::shm::{SegmentId, ShmReader};
use strata_net::{secret, tls, transport, Identity, NetConfig};
use strata_worker::affinity;
use tokio::sync::mpsc;
use tracing::{debug, info, warn};

/// How to run the workers (resolved from `[cluster]` and the command line).
#[derive(Clone, Debug)]
pub struct ClusterOptions {
    /// Number of workers.
    pub workers: usize,
    /// Spawn them locally (true) or wait for externally launched ones.
    pub spawn: bool,
    /// Listen address.
    pub listen: SocketAddr,
    /// k-d leaves per worker.
    pub leaves_per_worker: usize,
    /// Wait for workers to connect and set up.
    pub connect_timeout: Duration,
    /// Longest frame.
    pub frame_timeout: Duration,
    /// Connection idle timeout.
    pub idle_timeout: Duration,
    /// First QUIC datagram size (`cluster.quic_mtu`), of this endpoint and spawned workers.
    pub quic_mtu: u16,
    /// Rayon threads per spawned worker (0: divide the cores).
    pub worker_threads: usize,
    /// `cluster.pin_workers`: bind each spawned worker to its own block of CPUs.
    pub pin_workers: bool,
    /// Shared secret (None: generate one; only allowed when spawning).
    pub secret: Option<wire::Secret>,
    /// Where to write the fingerprint for launchers.
    pub fingerprint_file: Option<PathBuf>,
    /// Largest frame of the run (pixels): bounds piece sizes.
    pub max_pixels: u64,
    /// Executable for spawned workers (None: this executable's `worker` subcommand).
    pub worker_exe: Option<PathBuf>,
    /// Re-split when the measured imbalance exceeds this (0: never).
    pub rebalance_threshold: f64,
    /// How far a re-split follows the measurement, in (0, 1].
    pub rebalance_damping: f64,
    /// `cluster.rebalance_model`: divide each leaf's measured time by the pages its rays
    /// entered, or by its estimated boxes.
    pub rebalance_model: strata_common::scene::RebalanceModel,
    /// `cluster.rebalance_clock`: measure each leaf's cast by its CPU time over the
    /// worker's threads, or by its wall time.
    pub rebalance_clock: RebalanceClock,
    /// `cluster.transport`: shared memory between processes on one host, or QUIC.
    pub transport: Transport,
    /// `cluster.on_worker_loss`: re-render a frame without a worker that was lost, or fail.
    pub on_worker_loss: strata_common::scene::OnWorkerLoss,
    /// `cluster.replacement_wait_s`: how long a frame after a loss waits for a replacement.
    pub replacement_wait: Duration,
    /// `cluster.respawn`: lost local workers this run may replace by spawning new ones.
    pub respawn: u32,
    /// `cluster.occlusion`: cross-worker occlusion with every rendered frame.
    pub occlusion: bool,
    /// `cluster.occlusion_block`: side of its screen blocks in pixels.
    pub occlusion_block: u32,
    /// `cluster.occlusion_prepass`: a low-resolution first pass when there is no prediction.
    pub occlusion_prepass: bool,
    /// `cluster.occlusion_motion`: widen predictions by the scene's motion on screen.
    pub occlusion_motion: bool,
}

/// The first pass of cross-worker occlusion renders at 1/PREPASS_SCALE of the resolution
/// (1/16 of the rays).
pub const PREPASS_SCALE: u32 = 4;

/// Which displacement of the scene's points on screen between two frames widens the
/// occlusion prediction (`cluster.occlusion_motion`): the median. On the demo orbit (3° a
/// frame, 1280×720) the largest is about 48 pixels, dominated by the box's near corners,
/// and widening by it left 2.5 times fewer blocks out for 24 % more samples; the median
/// (13 pixels) cut the blocks cast again at p = 8 from about 30 000 to 1 000 per frame for
/// 7 % more samples, and the lower quartile to 3 000 for 4 %.
const MOTION_QUANTILE: f64 = 0.5;

/// The deadline a worker keeps for its own frame waits (its peers' pieces, its sends),
/// counted from when it receives the frame: shorter than the coordinator's
/// `cluster.frame_timeout_s`, by a fifth of it up to 10 s, so that a worker stuck with a
/// hung peer says which one (`WorkerMsg::Failed::suspects`) before the coordinator runs out
/// of time itself and, knowing only who has not answered, blames every worker still in the
/// exchange. (A worker waits for the coordinator's occlusion map longer than the frame
/// timeout: the coordinator blames that wait itself.)
pub fn worker_frame_timeout(frame_timeout: Duration) -> Duration {
    frame_timeout
        .saturating_sub((frame_timeout / 5).min(Duration::from_secs(10)))
        .max(Duration::from_millis(1))
}

/// The ranks a frame that ran out of time is blamed on (`missing`: those without a
/// result). While occlusion maps are still going out (`waiting_on`: the coverage by rank of
/// the phase under way), the workers behind one whose coverage is missing wait on it: those
/// are late, not the rest; the last worker of `order` sends no coverage and is not blamed
/// for it.
fn late_ranks(
    slots: &[u32],
    order: &[u32],
    waiting_on: Option<&[Option<Transmittance>]>,
    missing: Vec<u32>,
) -> Vec<u32> {
    let Some(cov) = waiting_on else {
        return missing;
    };
    let no_coverage: Vec<u32> = slots
        .iter()
        .copied()
        .filter(|&r| cov[r as usize].is_none() && order.last() != Some(&r))
        .collect();
    if no_coverage.is_empty() {
        missing
    } else {
        no_coverage
    }
}

/// The coverage by rank of the occlusion phase under way (the first pass's until its maps
/// went out, then the frame's), or `None` once every map went out.
fn occlusion_phase<'a>(
    pre_sent: bool,
    maps_sent: bool,
    pre_coverage: &'a [Option<Transmittance>],
    coverage: &'a [Option<Transmittance>],
) -> Option<&'a [Option<Transmittance>]> {
    if !pre_sent {
        Some(pre_coverage)
    } else if !maps_sent {
        Some(coverage)
    } else {
        None
    }
}

/// The ranks a worker's `Failed` is blamed on: its suspects in the frame (each once, never
/// itself), narrowed while occlusion maps are still going out (`waiting_on`: the coverage
/// by rank of the phase under way). A worker behind the front-most one whose coverage is
/// missing waits for its map, so its silence is that worker's doing: a peer that names it
/// (its pieces never came) blames the one it waits on instead. Without the narrowing the
/// peers of a hung worker blamed the healthy workers stuck behind it, and all were given up.
fn narrow_suspects(
    suspects: Vec<u32>,
    slots: &[u32],
    order: &[u32],
    rank: u32,
    waiting_on: Option<&[Option<Transmittance>]>,
) -> Vec<u32> {
    let mut lost: Vec<u32> = suspects
        .into_iter()
        .filter(|r| slots.contains(r) && *r != rank)
        .collect();
    lost.sort_unstable();
    lost.dedup();
    let Some(cov) = waiting_on else {
        return lost;
    };
    // The front-most worker whose coverage is missing (the last sends none).
    let Some(pb) = order[..order.len().saturating_sub(1)]
        .iter()
        .position(|&r| cov.get(r as usize).is_some_and(|c| c.is_none()))
    else {
        return lost;
    };
    let pos = |r: u32| order.iter().position(|&o| o == r).unwrap_or(usize::MAX);
    let narrowed: Vec<u32> = lost.iter().copied().filter(|&r| pos(r) <= pb).collect();
    if narrowed.is_empty() && !lost.is_empty() {
        vec![order[pb]]
    } else {
        narrowed
    }
}

/// Whether every rank of `b` has the same ranks in front of it as in `a` (their order among
/// themselves does not matter to opacity).
fn same_fronts(a: &[u32], b: &[u32]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    b.iter().all(|r| {
        let front = |o: &[u32]| -> Option<Vec<u32>> {
            let pos = o.iter().position(|x| x == r)?;
            let mut f = o[..pos].to_vec();
            f.sort_unstable();
            Some(f)
        };
        let fa = front(a);
        fa.is_some() && fa == front(b)
    })
}

/// A re-split of the k-d tree between two frames of a sequence.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Rebalance {
    /// The frame whose measurement triggered it (the new split applies from the next).
    pub after_frame: u64,
    /// Slowest worker's render time over the mean, measured on that frame.
    pub measured_imbalance: f64,
    /// The new split's imbalance under the same measurement, undamped (what the cost model
    /// expects of it; above 1 where damping corrects only part of the measured one).
    pub expected_imbalance: f64,
    /// What the measured time was divided by: `"pages"` (the pages the rays entered) or
    /// `"leaves"` (each leaf's estimated boxes, one factor per leaf).
    pub model: &'static str,
    /// The workers' page records the re-split used (0 for `"leaves"`).
    pub page_records: usize,
    /// The clock the leaves were measured by: `"cpu"` or `"wall"` (also where `cpu` was
    /// asked for but some worker reported no CPU times).
    pub clock: &'static str,
    /// Leaf regions before and after.
    pub old_leaves: Vec<strata_common::kd::Region>,
    /// After.
    pub new_leaves: Vec<strata_common::kd::Region>,
}

impl ClusterOptions {
    /// From the scene's `[cluster]` section, `--workers` and the image size.
    pub fn from_scene(scene: &Scene, workers: Option<usize>) -> Result<ClusterOptions> {
        let c = &scene.cluster;
        let workers = match workers.or((c.workers > 0).then_some(c.workers as usize)) {
            Some(n) => n,
            None => std::thread::available_parallelism()
                .map_or(2, |n| n.get())
                .clamp(2, 8),
        };
        anyhow::ensure!(
            (1..=256).contains(&workers),
            "cluster.workers must lie in 1..=256, got {workers}"
        );
        // The ranges of the section's values, as the scene file's parse checks them (a scene
        // built in code has not been parsed).
        c.check().map_err(|(_key, why)| anyhow!(why))?;
        let listen: SocketAddr = c.listen.parse().with_context(|| {
            format!(
                "cluster.listen = {:?}: expected IP:PORT, e.g. 0.0.0.0:7000",
                c.listen
            )
        })?;
        let secret =
            secret::read_secret(c.secret_file.as_deref(), secret::SECRET_ENV)?.map(wire::Secret);
        if !c.spawn && secret.is_none() {
            bail!(
                "cluster.spawn = false needs a shared secret: set cluster.secret_file or ${}",
                secret::SECRET_ENV
            );
        }
        Ok(ClusterOptions {
            workers,
            spawn: c.spawn,
            listen,
            leaves_per_worker: c.leaves_per_worker as usize,
            connect_timeout: Duration::from_secs_f64(c.connect_timeout_s),
            frame_timeout: Duration::from_secs_f64(c.frame_timeout_s),
            idle_timeout: Duration::from_secs_f64(c.idle_timeout_s),
            quic_mtu: c.quic_mtu,
            worker_threads: c.worker_threads as usize,
            pin_workers: c.pin_workers,
            secret,
            fingerprint_file: c.fingerprint_file.clone(),
            max_pixels: match &scene.wall {
                Some(w) => {
                    let (sw, sh) = w.geometry().stacked_size();
                    sw as u64 * sh as u64
                }
                None => scene.render.width as u64 * scene.render.height as u64,
            },
            rebalance_threshold: c.rebalance_threshold,
            rebalance_damping: c.rebalance_damping,
            rebalance_model: c.rebalance_model,
            rebalance_clock: c.rebalance_clock,
            transport: c.transport,
            on_worker_loss: c.on_worker_loss,
            replacement_wait: Duration::from_secs_f64(c.replacement_wait_s),
            respawn: c.respawn,
            occlusion: c.occlusion,
            occlusion_block: c.occlusion_block,
            occlusion_prepass: c.occlusion_prepass,
            occlusion_motion: c.occlusion_motion,
            worker_exe: std::env::var_os("STRATA_WORKER_BIN").map(PathBuf::from),
        })
    }
}

/// A connected worker.
struct Worker {
    rank: u32,
    name: String,
    pid: u32,
    addr: SocketAddr,
    fingerprint: wire::Fingerprint,
    conn: quinn::Connection,
    send: quinn::SendStream,
    /// Its shared-memory host id (see `strata_net::shm::host_id`).
    host: Option<String>,
    /// Its segment for final pieces, when it shares this host.
    shm: Option<ShmReader>,
    /// The set-up attempt its messages answer (its last `Meshing`).
    attempt: u32,
}

impl Worker {
    fn describe(&self) -> String {
        format!(
            "worker {} ({}, pid {}, {})",
            self.rank, self.name, self.pid, self.addr
        )
    }
}

enum Event {
    /// A worker's message; `_held` is its share of that worker's reader budget
    /// (`spawn_reader`), given back when the event is dropped.
    Msg {
        rank: u32,
        frame: strata_net::Frame,
        _held: tokio::sync::OwnedSemaphorePermit,
    },
    Lost {
        rank: u32,
        error: String,
    },
    Exited {
        child: usize,
        status: String,
    },
}

/// One frame's result.
pub struct FrameResult {
    /// The composited image, premultiplied, row-major.
    pub image: FrameImage,
    /// Per-worker stats, in slot order (the decomposition's workers).
    pub stats: Vec<WorkerFrameStats>,
    /// Coordinator's wall time for the frame.
    pub wall_s: f64,
    /// The whole compositing (exchange + gather), as IceT's frame time measures it: this
    /// coordinator's time from sending the frame requests (after its canvas is ready) to the
    /// last final piece, less the slowest worker's render (its render, first pass,
    /// occlusion wait and re-cast). Both are durations, each on one clock; no timestamp of
    /// one host is subtracted from another's. It includes the requests' sending and one
    /// request's latency, and a wall's tile writes on its drivers.
    pub composite_s: f64,
    /// Bytes of final pieces received (those written into the canvas counted as the f32
    /// pixels written).
    pub gather_bytes: u64,
    /// Workers whose final piece was written in place into the canvas.
    pub canvas_gather: usize,
    /// Of these, workers whose last round was blended straight into the canvas.
    pub canvas_blended: usize,
    /// Seconds this coordinator spent reading and checking final pieces (shared-memory
    /// reads and parsing; part of `composite_s`).
    pub collect_s: f64,
    /// Seconds assembling the final image from the pieces (after `composite_s`): checking
    /// the spans written into the canvas and placing pieces that came over the network.
    pub assemble_s: f64,
    /// Workers given up on during this frame (the frame was re-rendered without them).
    pub lost: Vec<LostWorker>,
    /// Workers that joined the running sequence before this frame.
    pub joined: Vec<JoinedWorker>,
    /// Seconds this coordinator spent checking occlusion coverage and sending the maps.
    pub occlusion_s: f64,
}

/// A composited frame: the run's shared canvas, which workers on this host wrote in place,
/// or an image assembled in memory. Either reads as the row-major pixels.
#[derive(Clone, Debug)]
pub enum FrameImage {
    /// Assembled in memory (no worker shares this host, or a wall frame's empty image).
    Owned(Vec<Rgba>),
    /// The canvas itself; it is not written again while this is held.
    Canvas(Arc<Canvas>),
}

impl std::ops::Deref for FrameImage {
    type Target = [Rgba];
    fn deref(&self) -> &[Rgba] {
        match self {
            FrameImage::Owned(v) => v,
            FrameImage::Canvas(c) => c.pixels(),
        }
    }
}

impl FrameImage {
    /// The pixels as an owned vector (a copy if they are in the canvas).
    pub fn into_vec(self) -> Vec<Rgba> {
        match self {
            FrameImage::Owned(v) => v,
            FrameImage::Canvas(c) => c.pixels().to_vec(),
        }
    }
}

/// How a worker's final piece arrived.
enum Final {
    /// Over the network or through its gather segment.
    Piece(SparsePiece),
    /// Written in place into the frame's canvas, covering this span.
    InCanvas(Span),
}

/// Completes a frame in `canvas`: pieces that came over the network or through gather
/// segments are placed; the spans written in place are checked (disjoint, inside the
/// frame) and what none covers is cleared.
fn finish_canvas(
    canvas: &mut Canvas,
    interlace: &Interlace,
    pieces: &[Final],
) -> Result<(), strata_common::composite::CompositeError> {
    let frame = canvas.pixels_mut();
    let mut spans = Vec::with_capacity(pieces.len());
    for p in pieces {
        match p {
            Final::Piece(p) => {
                composite_canvas::write_piece(frame, interlace, p)?;
                spans.push(p.span);
            }
            Final::InCanvas(s) => spans.push(*s),
        }
    }
    composite_canvas::finish(frame, interlace, &spans)
}

/// `composite` for a frame of `ranks` ranks: as it is where it can be planned; exact radix
/// factors (`composite.k` of two or more) that do not multiply to `ranks`, as happens after
/// a worker is lost or joins, become their largest as a target radix (automatic factors up
/// to it), with a warning. Checked at start-up for the run's first count.
fn composite_for(ranks: usize, composite: &CompositeChoice) -> CompositeChoice {
    if composite.plan(ranks, 1).is_ok() || composite.k.len() < 2 {
        return composite.clone();
    }
    let target = composite.k.iter().copied().max().unwrap_or(2).max(2);
    warn!(
        ranks,
        factors = ?composite.k,
        target,
        "composite.k does not multiply to the ranks in this frame: automatic factors up to the largest"
    );
    CompositeChoice {
        k: vec![target],
        ..composite.clone()
    }
}

/// Checks that each worker's final piece (`spans`, in the order of `slots`) covers the
/// part of the image the frame's compositing plan gives its position in `order`, as the
/// workers build it: the gather checks only that pieces lie in the frame and do not
/// overlap, so a worker returning less (a bug, or a lie) would leave a transparent stripe
/// in a frame reported as done. Returns the first rank whose piece differs, and why.
fn final_spans_match_the_plan(
    pixels: u32,
    composite: &CompositeChoice,
    order: &[u32],
    slots: &[u32],
    spans: &[Span],
) -> Result<(), (u32, anyhow::Error)> {
    let plan = composite.plan(order.len(), pixels);
    for (&rank, &span) in slots.iter().zip(spans) {
        let fail = |e: anyhow::Error| Err((rank, e));
        let Ok(plan) = &plan else {
            return fail(anyhow!("no compositing plan for {} ranks", order.len()));
        };
        let Some(pos) = order.iter().position(|&r| r == rank) else {
            return fail(anyhow!("not in the frame's visibility order"));
        };
        let want = plan.result[pos];
        if span != want && !(span.is_empty() && want.is_empty()) {
            return fail(anyhow!(
                "its final piece holds pixels {span}, not its part {want} of the image"
            ));
        }
    }
    Ok(())
}

/// A worker given up on.
#[derive(Clone, Debug, serde::Serialize)]
pub struct LostWorker {
    /// Its description (rank, name, pid, address).
    pub worker: String,
    /// Its rank.
    pub rank: u32,
    /// Why.
    pub reason: String,
    /// When it was lost: `"set-up"` or `"frame"`.
    pub phase: String,
    /// Seconds from the start of the frame (or of the set-up) to the failure that gave the
    /// worker up.
    pub detected_after_s: f64,
    /// Seconds from that failure to the frame completing without it (or to the workers
    /// left being ready).
    pub recovery_s: f64,
    /// The new assignment: each rank left and its leaf regions.
    pub assignment: Vec<Assignment>,
}

/// A worker that joined a running sequence (cluster mode) and took load.
#[derive(Clone, Debug, serde::Serialize)]
pub struct JoinedWorker {
    /// Its description (rank, name, pid, address).
    pub worker: String,
    /// Its rank.
    pub rank: u32,
    /// The first frame of the sequence it rendered (the caller, which numbers the
    /// sequence, fills it in).
    pub frame: u64,
    /// Seconds to set the run up again with it.
    pub setup_s: f64,
    /// The new assignment: each rank in the run and its leaf regions.
    pub assignment: Vec<Assignment>,
}

/// The leaf regions one rank renders.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Assignment {
    /// The rank.
    pub rank: u32,
    /// Its leaves.
    pub leaves: Vec<strata_common::kd::Region>,
}

/// A failed attempt at a frame and the workers it blames.
struct Failure {
    error: anyhow::Error,
    lost: Vec<u32>,
}

impl Failure {
    fn of(error: anyhow::Error) -> Failure {
        Failure {
            error,
            lost: Vec::new(),
        }
    }

    fn blaming(error: anyhow::Error, rank: u32) -> Failure {
        Failure {
            error,
            lost: vec![rank],
        }
    }
}

/// Which pairs of processes exchange through shared memory.
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct TransportReport {
    /// Worker pairs that exchange through shared memory.
    pub shm_pairs: usize,
    /// Worker pairs that exchange over QUIC.
    pub quic_pairs: usize,
    /// Workers whose final pieces reach the coordinator through shared memory.
    pub shm_gather: usize,
    /// Workers whose final pieces reach the coordinator over QUIC.
    pub quic_gather: usize,
}

impl TransportReport {
    /// One line for logs and summaries, e.g. `shared memory (3 pairs, 3 gathers)`.
    pub fn describe(&self) -> String {
        let part = |shm: usize, quic: usize, what: &str| match (shm, quic) {
            (0, 0) => None,
            (s, 0) => Some(format!("{s} {what} over shared memory")),
            (0, q) => Some(format!("{q} {what} over QUIC")),
            (s, q) => Some(format!("{s} {what} over shared memory, {q} over QUIC")),
        };
        [
            part(self.shm_pairs, self.quic_pairs, "pairs"),
            part(self.shm_gather, self.quic_gather, "gathers"),
        ]
        .into_iter()
        .flatten()
        .collect::<Vec<_>>()
        .join("; ")
    }
}

/// A running set of workers.
pub struct Cluster {
    ep: quinn::Endpoint,
    workers: Vec<Worker>,
    events: mpsc::UnboundedReceiver<Event>,
    decomposition: Decomposition,
    opts: ClusterOptions,
    frame_no: u64,
    /// The image size and visibility order of the last frame whose occlusion maps went
    /// out: the workers' predictions hold while both (the workers in front of each) stay.
    occlusion_last: Option<(u32, u32, Vec<u32>, Camera)>,
    /// The scene's render settings (the display map of [`View`]s made here).
    render: strata_common::scene::RenderSettings,
    /// Frame canvases in shared memory (`strata_net::canvas`) that workers on this host
    /// write their final spans into; one whose image a caller still holds is not reused.
    canvases: Vec<Arc<Canvas>>,
    /// The worker processes this process spawned, in spawn order (a child's number is its
    /// index here).
    children: Vec<SpawnedChild>,
    /// The cost boxes the decomposition balances (re-weighted by each re-split).
    costs: decompose::SceneCosts,
    /// The scene's estimated costs, as set-up computed them (what a re-split by measured
    /// pages divides a page's time by).
    estimate: decompose::SceneCosts,
    /// New leaves to hand each worker with its next frame request.
    new_leaves: Vec<Option<Vec<strata_common::kd::Region>>>,
    /// The transports chosen at set-up.
    transport: TransportReport,
    /// The ranks still in the run, in the order of the decomposition's workers (slot →
    /// rank); lost workers drop out.
    slots: Vec<u32>,
    /// The wall frame [`Cluster::frame_wall`] is rendering.
    wall: Option<WallJob>,
    /// Workers given up on during set-up, reported with the first frame.
    setup_lost: Vec<LostWorker>,
    /// The number of the next set-up attempt.
    setup_attempt: u32,
    /// The scene every set-up carries.
    scene_toml: String,
    /// `composite.lz4` of that scene: the workers' peer readers accept compressed pieces
    /// only in a run set up with it, so every frame must ask for the same.
    lz4: bool,
    /// Cluster mode: workers that authenticated after the run filled up, admitted as
    /// replacements at the start of a frame (or refused when the run is full), and the
    /// task accepting them.
    joiners: Option<mpsc::UnboundedReceiver<Authenticated>>,
    acceptor: Option<tokio::task::JoinHandle<()>>,
    /// Where the connection readers of newly admitted workers report.
    events_tx: mpsc::UnboundedSender<Event>,
    /// A worker was lost since the last frame began: that frame waits up to
    /// `cluster.replacement_wait_s` for a replacement (once).
    awaiting_replacement: bool,
    /// Local mode: how the workers were started, to start replacements.
    spawner: Option<Spawner>,
    /// Lost local workers that may still be replaced (`cluster.respawn`).
    respawns_left: u32,
    /// Pids of replacements spawned and not yet admitted: the next frame waits for them
    /// (while one of them is alive) up to `cluster.connect_timeout_s`.
    respawned: Vec<u32>,
}

impl Drop for Cluster {
    fn drop(&mut self) {
        if let Some(a) = &self.acceptor {
            a.abort();
        }
    }
}

/// A wall frame's layout and outputs, before drivers are chosen over the ranks left.
struct WallJob {
    settings: WallSettings,
    files: Vec<TileFiles>,
    background: [f32; 3],
}

impl WallJob {
    /// The frame's wall over the ranks `slots`: the scene's drivers, or the default spread
    /// over those ranks.
    fn frame(&self, slots: &[u32]) -> Result<WallFrame> {
        let g = self.settings.geometry();
        let drivers = match &self.settings.ranks {
            Some(r) => {
                if let Some(lost) = r.iter().find(|r| !slots.contains(r)) {
                    bail!("wall.ranks: rank {lost} drives tiles but is not in the run (ranks {slots:?})");
                }
                r.clone()
            }
            None => g
                .default_drivers(slots.len())
                .into_iter()
                .map(|i| slots[i as usize])
                .collect(),
        };
        let ranks = slots.iter().copied().max().map_or(0, |m| m as usize + 1);
        g.check_drivers(&drivers, ranks)?;
        Ok(WallFrame {
            geometry: g,
            drivers,
            files: self.files.clone(),
            background: self.background,
        })
    }
}

impl Cluster {
    /// Renders one frame of a powerwall: each tile's pixels are composited on the rank that
    /// drives it, which writes the tile's `files` (PNG flattened over `background`, and
    /// EXR); no process holds the whole wall. The result's `image` is empty.
    pub async fn frame_wall(
        &mut self,
        camera: &Camera,
        wall: &WallSettings,
        files: &[TileFiles],
        background: [f32; 3],
        composite: &CompositeChoice,
    ) -> Result<FrameResult> {
        let g = wall.geometry();
        g.check().map_err(|e| anyhow!(e))?;
        anyhow::ensure!(
            files.len() == g.tiles() as usize,
            "{} tile files for {} tiles",
            files.len(),
            g.tiles()
        );
        self.wall = Some(WallJob {
            settings: wall.clone(),
            files: files.to_vec(),
            background,
        });
        let (w, h) = g.stacked_size();
        let r = self
            .frame(camera, w, h, composite, FrameSource::Render)
            .await;
        self.wall = None;
        r
    }

    /// Decomposes the scene, starts (or awaits) the workers and sets them up.
    pub async fn start(scene: &Scene, opts: ClusterOptions) -> Result<Cluster> {
        let n = opts.workers;
        let costs = tokio::task::block_in_place(|| decompose::scene_costs(scene))?;
        let decomposition = Decomposition::balanced(
            costs.root,
            &costs.boxes,
            n,
            opts.leaves_per_worker,
            &costs.planes,
        );
        info!(
            workers = n,
            leaves = decomposition.tree.leaves.len(),
            imbalance = format!("{:.3}", decomposition.imbalance()),
            "k-d decomposition"
        );
        let id = Identity::generate()?;
        let net = NetConfig {
            idle_timeout: opts.idle_timeout,
            initial_mtu: opts.quic_mtu,
            // Workers present their certificates, which must be the ones their hellos
            // name (and the coordinator hands to their peers).
            client_auth: true,
            ..NetConfig::default()
        };
        let ep = transport::endpoint(opts.listen, &id, &net)?;
        let local = ep.local_addr()?;
        let fp = tls::to_hex(&id.fingerprint);
        info!(listen = %local, fingerprint = %fp, "coordinator listening");
        if let Some(f) = &opts.fingerprint_file {
            crate::synth::write_atomically(f, format!("{fp}\n").as_bytes())
                .with_context(|| format!("writing the fingerprint to {}", f.display()))?;
        }
        let secret = opts
            .secret
            .as_ref()
            .map_or_else(secret::new_secret, |s| s.0.clone());
        let (tx, events) = mpsc::unbounded_channel();
        let mut children = Vec::new();
        let spawner = match opts.spawn {
            true => Some(Spawner::new(&opts, n, local, &fp, &secret)?),
            false => None,
        };
        if let Some(sp) = &spawner {
            for i in 0..n {
                let (pid, kill) = sp.spawn(i, i, &tx)?;
                children.push(SpawnedChild { pid, kill, gpu: i });
            }
            info!(
                workers = n,
                threads_each = sp.threads,
                pinned = sp.pin.is_some(),
                "spawned local workers"
            );
        } else {
            info!(
                "waiting for {n} workers: start them with `worker --connect HOST:{} --fingerprint {fp} --secret-file FILE`",
                local.port()
            );
        }
        let respawns_left = if spawner.is_some() { opts.respawn } else { 0 };
        let mut cluster = Cluster {
            ep,
            workers: Vec::new(),
            events,
            decomposition,
            opts,
            frame_no: 0,
            occlusion_last: None,
            render: scene.render.clone(),
            canvases: Vec::new(),
            wall: None,
            children,
            estimate: costs.clone(),
            costs,
            new_leaves: vec![None; n],
            transport: TransportReport::default(),
            slots: (0..n as u32).collect(),
            setup_lost: Vec::new(),
            setup_attempt: 0,
            scene_toml: scene.to_toml().map_err(|e| anyhow!(e))?,
            lz4: scene.composite.lz4,
            joiners: None,
            acceptor: None,
            events_tx: tx.clone(),
            awaiting_replacement: false,
            respawns_left,
            spawner,
            respawned: Vec::new(),
        };
        cluster.gather_workers(&secret, &tx).await?;
        cluster.setup(&[]).await?;
        Ok(cluster)
    }

    fn child_name(&self, child: usize) -> String {
        let pid = self.children.get(child).map_or(0, |c| c.pid);
        match self.workers.iter().find(|w| w.pid == pid) {
            Some(w) => w.describe(),
            None => format!("local worker process {child} (pid {pid})"),
        }
    }

    /// Accepts connections until `workers` have authenticated, refusing (and logging) any
    /// that fail the secret, the protocol version or the frame limits.
    async fn gather_workers(
        &mut self,
        secret: &[u8],
        tx: &mpsc::UnboundedSender<Event>,
    ) -> Result<()> {
        let n = self.opts.workers;
        let (auth_tx, mut auth_rx) = mpsc::unbounded_channel();
        let ep = self.ep.clone();
        let secret_owned = secret.to_vec();
        // At most this many handshakes at once (every worker of the run at once, and some
        // to spare); strangers cannot queue unbounded work.
        let pending = std::sync::Arc::new(tokio::sync::Semaphore::new((n + 16).max(64)));
        let acceptor = tokio::spawn(async move {
            while let Some(incoming) = ep.accept().await {
                let Ok(permit) = pending.clone().try_acquire_owned() else {
                    warn!(remote = %incoming.remote_address(), "refused a connection: too many handshakes in progress");
                    incoming.refuse();
                    continue;
                };
                let auth_tx = auth_tx.clone();
                let secret = secret_owned.clone();
                tokio::spawn(async move {
                    let remote = incoming.remote_address();
                    match authenticate(incoming, &secret).await {
                        Ok(w) => {
                            let _ = auth_tx.send(w);
                        }
                        Err(e) => warn!(%remote, "refused a connection: {e:#}"),
                    }
                    drop(permit);
                });
            }
        });
        let deadline = Instant::now() + self.opts.connect_timeout;
        while self.workers.len() < n {
            let left = deadline.saturating_duration_since(Instant::now());
            tokio::select! {
                w = auth_rx.recv() => {
                    let (name, pid, fingerprint, host, conn, send, recv) = w.ok_or_else(|| anyhow!("the listener stopped"))?;
                    let rank = self.workers.len() as u32;
                    transport::trust(&conn);
                    // Peers dial this address; an IPv4 worker on a dual-stack listener
                    // shows up as ::ffff:a.b.c.d, which an IPv4 socket cannot dial.
                    let remote = conn.remote_address();
                    let addr = SocketAddr::new(remote.ip().to_canonical(), remote.port());
                    info!(rank, %name, pid, %addr, "worker joined");
                    spawn_reader(rank, conn.clone(), recv, Limits::for_pixels(self.opts.max_pixels), tx.clone(), self.opts.idle_timeout);
                    self.workers.push(Worker { rank, name, pid, addr, fingerprint, conn, send, host, shm: None, attempt: 0 });
                }
                ev = self.events.recv() => {
                    acceptor.abort();
                    return Err(match ev {
                        Some(Event::Exited { child, status }) => anyhow!(
                            "{} exited before the run started: {status}",
                            self.child_name(child)
                        ),
                        Some(Event::Lost { rank, error }) => anyhow!(
                            "{} disconnected before the run started: {error}",
                            self.workers[rank as usize].describe()
                        ),
                        Some(Event::Msg { rank, frame, .. }) => {
                            match wire::decode_meta::<WorkerMsg>(&frame.meta) {
                                Ok(WorkerMsg::Failed { message, .. }) => anyhow!(
                                    "{} failed: {message}",
                                    self.workers[rank as usize].describe()
                                ),
                                _ => anyhow!(
                                    "{} spoke out of turn before the run started",
                                    self.workers[rank as usize].describe()
                                ),
                            }
                        }
                        None => anyhow!("event channel closed"),
                    });
                }
                _ = tokio::time::sleep(left) => {
                    acceptor.abort();
                    bail!(
                        "only {} of {n} workers connected within {:.0} s (cluster.connect_timeout_s)",
                        self.workers.len(),
                        self.opts.connect_timeout.as_secs_f64()
                    );
                }
            }
        }
        self.acceptor = Some(acceptor);
        self.settle_joiners(auth_rx).await;
        Ok(())
    }

    /// Cluster mode, or local mode with `cluster.respawn` left: keeps `rx`, so that later
    /// workers may replace lost ones (or are refused while the run is full) at the start of
    /// a frame. Otherwise the run takes no one else: no new connections, and those that
    /// authenticated meanwhile are told the run is full.
    async fn settle_joiners(&mut self, mut rx: mpsc::UnboundedReceiver<Authenticated>) {
        if self.opts.spawn && self.respawns_left == 0 {
            if let Some(a) = self.acceptor.take() {
                a.abort();
            }
            self.ep.set_server_config(None);
            while let Ok(j) = rx.try_recv() {
                refuse_full(j, self.opts.workers).await;
            }
        } else {
            self.joiners = Some(rx);
        }
    }

    /// Cluster mode, at the start of a frame: admits the workers that connected since as
    /// replacements while the run has fewer than `cluster.workers` (after a loss, waiting
    /// up to `cluster.replacement_wait_s` for one), refuses the others, and sets the run up
    /// again with the newcomers. Returns who joined.
    async fn admit_joiners(&mut self) -> Result<Vec<JoinedWorker>> {
        let Some(mut rx) = self.joiners.take() else {
            return Ok(Vec::new());
        };
        let want = self.opts.workers;
        // Only the frame after a loss waits; later ones take a replacement when it comes.
        // Replacements this coordinator spawned itself are waited for as the first
        // workers were (they are ours, and were started for this).
        let spawned = !self.respawned.is_empty();
        let wait = match (self.awaiting_replacement, spawned) {
            (_, true) => self.opts.replacement_wait.max(self.opts.connect_timeout),
            (true, false) => self.opts.replacement_wait,
            (false, false) => Duration::ZERO,
        };
        let deadline = Instant::now()
            + if self.slots.len() < want {
                wait
            } else {
                Duration::ZERO
            };
        self.awaiting_replacement = false;
        let mut fresh = Vec::new();
        loop {
            // Spawned replacements are waited for only while one of them has not joined
            // and is still alive (checked every 50 ms: one that died never connects).
            let waiting = !spawned || self.respawned.iter().any(|&p| process_alive(p));
            let j = match rx.try_recv() {
                Ok(j) => j,
                Err(_) if self.slots.len() < want && Instant::now() < deadline && waiting => {
                    let mut left = deadline.saturating_duration_since(Instant::now());
                    if spawned {
                        left = left.min(Duration::from_millis(50));
                    }
                    match tokio::time::timeout(left, rx.recv()).await {
                        Ok(Some(j)) => j,
                        Ok(None) => break,
                        Err(_) => continue,
                    }
                }
                Err(_) => break,
            };
            if self.slots.len() >= want {
                refuse_full(j, want).await;
                continue;
            }
            // A process of ours that died after it connected (SIGKILL sends no close).
            if self.children.iter().any(|c| c.pid == j.1) && !process_alive(j.1) {
                info!(name = %j.0, pid = j.1, "a spawned worker exited before it was admitted");
                self.respawned.retain(|&p| p != j.1);
                continue;
            }
            // One that gave up waiting to be admitted is gone already.
            if let Some(why) = j.4.close_reason() {
                info!(name = %j.0, pid = j.1, "a worker that connected left before it was admitted: {why}");
                continue;
            }
            // `cluster.transport = "shm"` runs on one host only.
            if self.opts.transport == Transport::Shm && j.3 != strata_net::shm::host_id() {
                let (name, pid, _, _, conn, mut send, _) = j;
                warn!(%name, pid, "refused a worker: cluster.transport = \"shm\" and it is on another host");
                let msg = wire::encode_meta(&CoordMsg::Refused {
                    reason:
                        "cluster.transport = \"shm\" needs every process on the coordinator's host"
                            .into(),
                });
                let _ =
                    tokio::time::timeout(Duration::from_secs(1), write_frame(&mut send, &msg, &[]))
                        .await;
                let _ = send.finish();
                conn.close(6u32.into(), b"wrong host");
                continue;
            }
            let (name, pid, fingerprint, host, conn, send, recv) = j;
            let rank = self.workers.len() as u32;
            transport::trust(&conn);
            let remote = conn.remote_address();
            let addr = SocketAddr::new(remote.ip().to_canonical(), remote.port());
            info!(rank, %name, pid, %addr, "worker joined the running sequence");
            spawn_reader(
                rank,
                conn.clone(),
                recv,
                Limits::for_pixels(self.opts.max_pixels),
                self.events_tx.clone(),
                self.opts.idle_timeout,
            );
            self.workers.push(Worker {
                rank,
                name,
                pid,
                addr,
                fingerprint,
                conn,
                send,
                host,
                shm: None,
                attempt: 0,
            });
            self.slots.push(rank);
            self.new_leaves.push(None);
            self.respawned.retain(|&p| p != pid);
            fresh.push(rank);
        }
        // Spawned replacements have joined, or had their wait.
        self.respawned.clear();
        // Local mode with its replacements used up takes no one else.
        self.settle_joiners(rx).await;
        if fresh.is_empty() {
            return Ok(Vec::new());
        }
        let t0 = Instant::now();
        self.resplit();
        self.setup(&fresh).await?;
        let setup_s = t0.elapsed().as_secs_f64();
        // Who renders what now (after any loss during that set-up).
        let assignment = self.assignment();
        // Newcomers that failed their set-up were given up on again.
        Ok(fresh
            .into_iter()
            .filter(|r| self.slots.contains(r))
            .map(|r| JoinedWorker {
                worker: self.workers[r as usize].describe(),
                rank: r,
                frame: 0,
                setup_s,
                assignment: assignment.clone(),
            })
            .collect())
    }

    /// Sends every worker its set-up and waits until all have meshed with their peers.
    /// With `cluster.on_worker_loss = "reassign"`, a worker lost on the way (its process
    /// exited, its connection died, or it hung: its peers could not mesh with it, or the
    /// set-up ran out of time) is given up on, the scene is split over the workers left,
    /// and they are set up again without it.
    ///
    /// `fresh` are workers that joined a running sequence: one that fails its set-up is
    /// given up on whatever `cluster.on_worker_loss` says, never the run.
    async fn setup(&mut self, fresh: &[u32]) -> Result<()> {
        let t0 = Instant::now();
        // Losses of an earlier set-up not yet reported (a joiner's set-up before the first
        // frame) keep their recovery time: it was measured from their own set-up's start.
        let earlier = self.setup_lost.len();
        let scene_toml = self.scene_toml.clone();
        let (shm, gather) = self.plan_transport()?;
        // The ranks in the run only (workers given up on stay in `workers`): counted again
        // once the set-up is done, since it may give up more.
        let report = |slots: &[u32]| {
            let shm_pairs = slots
                .iter()
                .enumerate()
                .map(|(i, &a)| {
                    slots[i + 1..]
                        .iter()
                        .filter(|&&b| shm[a as usize][b as usize])
                        .count()
                })
                .sum();
            let n = slots.len();
            let shm_gather = slots.iter().filter(|&&r| gather[r as usize]).count();
            TransportReport {
                shm_pairs,
                quic_pairs: n * n.saturating_sub(1) / 2 - shm_pairs,
                shm_gather,
                quic_gather: n - shm_gather,
            }
        };
        self.transport = report(&self.slots);
        info!(transport = %self.transport.describe(), "transports chosen");
        loop {
            let (lost, error) = match self.setup_once(&scene_toml, &shm, &gather, fresh).await? {
                None => break,
                Some(l) => l,
            };
            let reassign = self.opts.on_worker_loss == strata_common::scene::OnWorkerLoss::Reassign;
            let only_fresh = lost.iter().all(|r| fresh.contains(r));
            if (!reassign && !only_fresh) || lost.len() >= self.slots.len() {
                return Err(error);
            }
            let names = self.list(lost.iter().map(|&r| r as usize));
            warn!("{error:#}; setting the run up again without {names}");
            let detected_after_s = t0.elapsed().as_secs_f64();
            let assignment = self.drop_workers(&lost).await;
            for &r in &lost {
                self.setup_lost.push(LostWorker {
                    worker: self.workers[r as usize].describe(),
                    rank: r,
                    reason: format!("{error:#}"),
                    phase: "set-up".into(),
                    detected_after_s,
                    recovery_s: 0.0,
                    assignment: assignment.clone(),
                });
            }
        }
        let ready_s = t0.elapsed().as_secs_f64();
        for l in &mut self.setup_lost[earlier..] {
            l.recovery_s = ready_s - l.detected_after_s;
        }
        self.transport = report(&self.slots);
        info!(workers = self.slots.len(), "all workers ready");
        Ok(())
    }

    /// One attempt at the set-up of the ranks in the run: `None` when all are ready, or
    /// the workers lost on the way and why. Errors that no loss explains (a worker that
    /// cannot open the scene, a malformed message) end the run.
    async fn setup_once(
        &mut self,
        scene_toml: &str,
        shm: &[Vec<bool>],
        gather: &[bool],
        fresh: &[u32],
    ) -> Result<Option<(Vec<u32>, anyhow::Error)>> {
        let peers: Vec<PeerInfo> = self
            .workers
            .iter()
            .map(|w| PeerInfo {
                addr: w.addr.to_string(),
                fingerprint: w.fingerprint,
                name: w.name.clone(),
            })
            .collect();
        let token = secret::random_bytes::<32>();
        let attempt = self.setup_attempt;
        self.setup_attempt += 1;
        let slots = self.slots.clone();
        let absent: Vec<u32> = (0..self.workers.len() as u32)
            .filter(|r| !slots.contains(r))
            .collect();
        for (slot, &rank) in slots.iter().enumerate() {
            // The set-up carries the current split: no new leaves with the next frame.
            self.new_leaves[rank as usize] = None;
            let leaves = self.slot_leaves(slot);
            let w = &mut self.workers[rank as usize];
            // A worker set up again announces a new segment.
            w.shm = None;
            let setup = CoordMsg::Setup(Box::new(Setup {
                rank,
                scene_toml: scene_toml.to_string(),
                leaves,
                peers: peers.clone(),
                run_token: token,
                max_pixels: self.opts.max_pixels,
                timeout_ms: worker_frame_timeout(self.opts.frame_timeout).as_millis() as u64,
                shm_peers: shm[rank as usize].clone(),
                shm_gather: gather[rank as usize],
                absent: absent.clone(),
                attempt,
                next_frame: self.frame_no,
            }));
            let what = w.describe();
            if let Err(e) = with_timeout(
                self.opts.connect_timeout,
                format!("sending the set-up to {what}"),
                write_frame(&mut w.send, &wire::encode_meta(&setup), &[]),
            )
            .await
            {
                return Ok(Some((vec![rank], anyhow!("{e}"))));
            }
        }
        let n = self.workers.len();
        let mut state: Vec<Answer> = (0..n).map(|_| Answer::Waiting).collect();
        let mut lost: Vec<(u32, String)> = Vec::new();
        // A worker's mesh gives up within its connect timeout of receiving the set-up (a
        // scene to parse comes first): the coordinator waits out two, so that the workers'
        // failures, which name whom they could not reach, come before its own deadline.
        let deadline = Instant::now() + 2 * self.opts.connect_timeout + Duration::from_secs(5);
        loop {
            // A loss ends the attempt at once: the workers left are set up again (a new
            // set-up replaces a mesh in progress), not kept waiting on the lost one.
            if !lost.is_empty() {
                let ranks: Vec<u32> = lost.iter().map(|l| l.0).collect();
                let why = lost
                    .iter()
                    .map(|(r, m)| {
                        format!(
                            "{} was lost during set-up: {m}",
                            self.workers[*r as usize].describe()
                        )
                    })
                    .collect::<Vec<_>>()
                    .join("; ");
                return Ok(Some((ranks, anyhow!("{why}"))));
            }
            let waiting: Vec<u32> = match setup_blame::judge(&slots, &state, fresh) {
                Verdict::Ready => return Ok(None),
                Verdict::Fail(r, msg) => {
                    bail!(
                        "{} failed to set up: {msg}",
                        self.workers[r as usize].describe()
                    )
                }
                Verdict::GiveUp(blamed) => {
                    for b in blamed {
                        let who = self.workers[b.by as usize].describe();
                        lost.push((
                            b.rank,
                            if b.silent {
                                format!("{who} could not mesh with it: {}", b.message)
                            } else {
                                format!(
                                    "{} of its peers could not mesh with it ({who}: {})",
                                    b.count, b.message
                                )
                            },
                        ));
                    }
                    continue;
                }
                Verdict::Wait => slots
                    .iter()
                    .copied()
                    .filter(|&r| state[r as usize] == Answer::Waiting)
                    .collect(),
            };
            let ev = match self.next_event(deadline).await {
                Ok(ev) => ev,
                Err(()) => {
                    // Out of time: the workers still silent are given up on.
                    let secs = self.opts.connect_timeout.as_secs_f64();
                    for r in waiting {
                        lost.push((
                            r,
                            format!("it did not finish its set-up within {secs:.0} s"),
                        ));
                    }
                    continue;
                }
            };
            match ev {
                Event::Msg { rank, .. } | Event::Lost { rank, .. } if !slots.contains(&rank) => {
                    debug!(rank, "ignoring a worker given up on");
                }
                Event::Exited { child, status }
                    if !self.child_rank(child).is_some_and(|r| slots.contains(&r)) =>
                {
                    debug!(child, %status, "a worker given up on has exited");
                }
                Event::Lost { rank, error } => lost.push((rank, format!("disconnected: {error}"))),
                Event::Exited { child, status } => {
                    let rank = self.child_rank(child).expect("a rank in the run");
                    lost.push((rank, format!("exited: {status}")));
                }
                Event::Msg { rank, frame, .. } => match wire::decode_meta::<WorkerMsg>(&frame.meta)
                {
                    Ok(WorkerMsg::Meshing { attempt: a }) => {
                        self.workers[rank as usize].attempt = a
                    }
                    // Answers to a set-up this one replaced.
                    Ok(
                        WorkerMsg::Ready
                        | WorkerMsg::ShmSegment { .. }
                        | WorkerMsg::Failed { frame: None, .. },
                    ) if self.workers[rank as usize].attempt != attempt => {
                        debug!(rank, "ignoring an answer to an earlier set-up");
                    }
                    Ok(WorkerMsg::Ready) => {
                        let w = &self.workers[rank as usize];
                        if gather[rank as usize] && w.shm.is_none() {
                            let e = anyhow!(
                                "{} is ready without announcing its shared-memory segment",
                                w.describe()
                            );
                            give_up_fresh(fresh, rank, e, &mut lost)?;
                        } else {
                            state[rank as usize] = Answer::Ready;
                        }
                    }
                    Ok(WorkerMsg::ShmSegment { name, pid, fd })
                        if gather[rank as usize] && self.workers[rank as usize].shm.is_none() =>
                    {
                        let w = &mut self.workers[rank as usize];
                        let id = SegmentId { name, pid, fd };
                        match tokio::task::block_in_place(|| ShmReader::open(&id)) {
                            Ok(r) => w.shm = Some(r),
                            Err(e) => {
                                let e = anyhow!(e).context(format!(
                                    "the shared-memory segment of {}",
                                    w.describe()
                                ));
                                give_up_fresh(fresh, rank, e, &mut lost)?;
                            }
                        }
                    }
                    // A newcomer that cannot set up is given up on, not the run.
                    Ok(WorkerMsg::Failed {
                        frame: None,
                        message,
                        ..
                    }) if fresh.contains(&rank) => {
                        lost.push((rank, format!("failed to set up: {message}")))
                    }
                    Ok(WorkerMsg::Failed {
                        frame: None,
                        message,
                        suspects,
                    }) => state[rank as usize] = Answer::Failed(message, suspects),
                    // A frame's leftovers cannot come before the first frame.
                    Ok(other) => {
                        let e = anyhow!(
                            "{} sent {other:?} during set-up",
                            self.workers[rank as usize].describe()
                        );
                        give_up_fresh(fresh, rank, e, &mut lost)?;
                    }
                    Err(e) => {
                        let e = anyhow!(
                            "{} sent a malformed message: {e}",
                            self.workers[rank as usize].describe()
                        );
                        give_up_fresh(fresh, rank, e, &mut lost)?;
                    }
                },
            }
        }
    }

    fn list(&self, ranks: impl Iterator<Item = usize>) -> String {
        ranks
            .map(|r| self.workers[r].describe())
            .collect::<Vec<_>>()
            .join(", ")
    }

    async fn next_event(&mut self, deadline: Instant) -> Result<Event, ()> {
        let left = deadline.saturating_duration_since(Instant::now());
        match tokio::time::timeout(left, self.events.recv()).await {
            Ok(Some(ev)) => Ok(ev),
            _ => Err(()),
        }
    }

    /// The error an unexpected event means.
    fn event_error(&self, ev: Event) -> anyhow::Error {
        match ev {
            Event::Lost { rank, error } => anyhow!(
                "{} disconnected: {error}",
                self.workers[rank as usize].describe()
            ),
            Event::Exited { child, status } => {
                anyhow!("{} exited: {status}", self.child_name(child))
            }
            Event::Msg { rank, .. } => anyhow!(
                "{} sent a message out of turn",
                self.workers[rank as usize].describe()
            ),
        }
    }

    /// Which links go through shared memory: per pair of workers (by rank), and per worker
    /// for the gather into this coordinator. Two processes share memory when they report
    /// the same host id; `cluster.transport = "quic"` uses none, `"shm"` requires all.
    fn plan_transport(&self) -> Result<(Vec<Vec<bool>>, Vec<bool>)> {
        let n = self.workers.len();
        let own = strata_net::shm::host_id();
        let shares = |a: &Option<String>, b: &Option<String>| {
            self.opts.transport != Transport::Quic && a.is_some() && a == b
        };
        let mut pairs = vec![vec![false; n]; n];
        let mut gather = vec![false; n];
        for (a, wa) in self.workers.iter().enumerate() {
            gather[a] = shares(&wa.host, &own);
            if self.opts.transport == Transport::Shm && !gather[a] {
                bail!(
                    "cluster.transport = \"shm\" needs every process on one host, but {} does not share this coordinator's shared memory",
                    wa.describe()
                );
            }
            for (b, wb) in self.workers.iter().enumerate() {
                pairs[a][b] = a != b && shares(&wa.host, &wb.host);
            }
        }
        Ok((pairs, gather))
    }

    /// The transports chosen at set-up.
    pub fn transport(&self) -> &TransportReport {
        &self.transport
    }

    /// Number of workers still in the run.
    pub fn workers(&self) -> usize {
        self.slots.len()
    }

    /// Largest final piece a worker may send.
    fn piece_limit(&self) -> u64 {
        Limits::for_pixels(self.opts.max_pixels).max_bulk
    }

    /// The decomposition in use.
    pub fn decomposition(&self) -> &Decomposition {
        &self.decomposition
    }

    /// Renders and composites one frame. With `cluster.on_worker_loss = "reassign"`, a worker lost on the way
    /// (its process exited, its connection died, it stopped answering within the frame
    /// timeout, or its peers lost it mid-exchange) costs a re-render, not the frame: it is
    /// killed (local) or disconnected, its leaves go to the survivors (a new k-d split
    /// over them; they open the same stores), compositing is re-planned for the ranks
    /// left, and the frame runs again. Later frames continue with the ranks left.
    pub async fn frame(
        &mut self,
        camera: &Camera,
        width: u32,
        height: u32,
        composite: &CompositeChoice,
        source: FrameSource,
    ) -> Result<FrameResult> {
        let joined = self.admit_joiners().await?;
        let t0 = Instant::now();
        let mut lost_here: Vec<LostWorker> = Vec::new();
        loop {
            match self
                .frame_once(camera, width, height, composite, source.clone())
                .await
            {
                Ok(mut r) => {
                    r.wall_s = t0.elapsed().as_secs_f64();
                    for l in &mut lost_here {
                        l.recovery_s = r.wall_s - l.detected_after_s;
                    }
                    // Losses during set-up are reported with the first frame.
                    let mut lost = std::mem::take(&mut self.setup_lost);
                    lost.extend(lost_here);
                    r.lost = lost;
                    r.joined = joined;
                    return Ok(r);
                }
                Err(f) => {
                    let lost: Vec<u32> = f
                        .lost
                        .iter()
                        .copied()
                        .filter(|r| self.slots.contains(r))
                        .collect();
                    let reassign =
                        self.opts.on_worker_loss == strata_common::scene::OnWorkerLoss::Reassign;
                    if !reassign || lost.is_empty() || lost.len() >= self.slots.len() {
                        return Err(f.error);
                    }
                    let names = self.list(lost.iter().map(|&r| r as usize));
                    warn!("{:#}; re-rendering the frame without {names}", f.error);
                    let detected_after_s = t0.elapsed().as_secs_f64();
                    let assignment = self.drop_workers(&lost).await;
                    for &r in &lost {
                        lost_here.push(LostWorker {
                            worker: self.workers[r as usize].describe(),
                            rank: r,
                            reason: format!("{:#}", f.error),
                            phase: "frame".into(),
                            detected_after_s,
                            recovery_s: 0.0,
                            assignment: assignment.clone(),
                        });
                    }
                }
            }
        }
    }

    /// Local mode with `cluster.respawn`: starts up to `lost` new worker processes (within
    /// what is left of the run's allowance) to take the places of lost ones; they join at
    /// the start of the next frame ([`admit_joiners`](Self::admit_joiners)).
    /// Each takes the GPU slot of the worker it replaces (`gpu_slots`).
    fn respawn(&mut self, gpu_slots: &[usize]) {
        let Some(sp) = &self.spawner else { return };
        for &gpu in gpu_slots.iter().take(self.respawns_left as usize) {
            let child = self.children.len();
            match sp.spawn(child, gpu, &self.events_tx) {
                Ok((pid, kill)) => {
                    info!(child, pid, "spawned a replacement worker (cluster.respawn)");
                    self.children.push(SpawnedChild { pid, kill, gpu });
                    self.respawns_left -= 1;
                    self.respawned.push(pid);
                }
                Err(e) => {
                    warn!("could not spawn a replacement worker: {e:#}");
                    return;
                }
            }
        }
    }

    /// Gives up on `lost` workers: kills (local) or disconnects them and splits the scene
    /// over the ranks left; returns the new assignment.
    async fn drop_workers(&mut self, lost: &[u32]) -> Vec<Assignment> {
        for &r in lost {
            self.kill_child(self.workers[r as usize].pid);
            let w = &mut self.workers[r as usize];
            w.conn.close(7u32.into(), b"lost");
            // Its gather segment goes with it (the mapping would keep the memory alive).
            w.shm = None;
        }
        self.slots.retain(|r| !lost.contains(r));
        self.awaiting_replacement = true;
        // A replacement takes the GPU slot of the worker it replaces.
        let gpu_slots: Vec<usize> = lost
            .iter()
            .map(|&r| {
                let pid = self.workers[r as usize].pid;
                self.children
                    .iter()
                    .rfind(|c| c.pid == pid)
                    .map_or(r as usize, |c| c.gpu)
            })
            .collect();
        self.respawn(&gpu_slots);
        // Survivors still waiting on a lost peer in the failed attempt stop at once.
        for &rank in &self.slots.clone() {
            let w = &mut self.workers[rank as usize];
            for &r in lost {
                let msg = wire::encode_meta(&CoordMsg::PeerLost { rank: r });
                let _ = tokio::time::timeout(
                    Duration::from_secs(2),
                    write_frame(&mut w.send, &msg, &[]),
                )
                .await;
            }
        }
        self.resplit()
    }

    /// Splits the scene over the ranks in the run (after a loss or a join): each gets its
    /// new leaves with its next set-up or frame request. Returns the new assignment.
    fn resplit(&mut self) -> Vec<Assignment> {
        let m = self.slots.len();
        let new = Decomposition::balanced(
            self.costs.root,
            &self.costs.boxes,
            m,
            self.opts.leaves_per_worker,
            &self.costs.planes,
        );
        info!(
            workers = m,
            imbalance = format!("{:.3}", new.imbalance()),
            "re-split the scene over the workers in the run"
        );
        self.decomposition = new;
        for (slot, &rank) in self.slots.clone().iter().enumerate() {
            self.new_leaves[rank as usize] = Some(self.slot_leaves(slot));
        }
        self.assignment()
    }

    /// The leaf regions of the decomposition's worker `slot`.
    fn slot_leaves(&self, slot: usize) -> Vec<strata_common::kd::Region> {
        let d = &self.decomposition;
        d.worker_leaves(slot)
            .into_iter()
            .map(|l| d.tree.leaves[l])
            .collect()
    }

    /// Each rank in the run and the leaf regions it renders.
    fn assignment(&self) -> Vec<Assignment> {
        self.slots
            .iter()
            .enumerate()
            .map(|(slot, &rank)| Assignment {
                rank,
                leaves: self.slot_leaves(slot),
            })
            .collect()
    }

    /// A canvas of `width × height` no caller holds, from the pool or new (`None`, with a
    /// warning, if shared memory fails: the pieces are then assembled). Taken out of the
    /// pool for the frame: a failed attempt drops it, so a worker given up on that still
    /// has it mapped writes into nothing anyone reads.
    fn take_canvas(&mut self, width: u32, height: u32) -> Option<Canvas> {
        /// Unheld canvases kept for reuse (a caller writing outputs while the next frame
        /// renders holds one more).
        const KEEP: usize = 2;
        let free = |c: &Arc<Canvas>| Arc::strong_count(c) == 1;
        if let Some(i) = self
            .canvases
            .iter()
            .position(|c| free(c) && c.size() == (width, height))
        {
            return Arc::try_unwrap(self.canvases.swap_remove(i)).ok();
        }
        // Forget unheld canvases of other sizes, and keep only a few of this one.
        self.canvases
            .retain(|c| !free(c) || c.size() == (width, height));
        while self.canvases.iter().filter(|c| free(c)).count() >= KEEP {
            let i = self.canvases.iter().position(free).expect("counted");
            self.canvases.swap_remove(i);
        }
        Canvas::create(width, height)
            .map_err(|e| warn!("no canvas for the frame, assembling pieces instead: {e}"))
            .ok()
    }

    /// One attempt at a frame; a failure lists the workers it blames.
    async fn frame_once(
        &mut self,
        camera: &Camera,
        width: u32,
        height: u32,
        composite: &CompositeChoice,
        source: FrameSource,
    ) -> Result<FrameResult, Failure> {
        let t0 = Instant::now();
        let pixels = width as u64 * height as u64;
        if pixels > self.opts.max_pixels {
            return Err(Failure::of(anyhow!(
                "frame of {width}x{height} exceeds the run's {} pixels",
                self.opts.max_pixels
            )));
        }
        if composite.lz4 != self.lz4 {
            return Err(Failure::of(anyhow!(
                "composite.lz4 is {} for this run's workers (set up from its scene); a frame cannot ask for {}",
                self.lz4,
                composite.lz4
            )));
        }
        let frame = self.frame_no;
        self.frame_no += 1;
        let slots = self.slots.clone();
        let order: Vec<u32> = self
            .decomposition
            .worker_order(camera.eye)
            .into_iter()
            .map(|slot| slots[slot])
            .collect();
        debug!(frame, ?order, "visibility order");
        // After a loss or a join the exact radix factors of `composite.k` may no longer
        // multiply to the ranks in the frame: it then takes the largest of them as a target.
        let composite = &composite_for(order.len(), composite);
        // Cross-worker occlusion in blocks of `occlusion_block` pixels, coarser where the
        // maps (two bytes a block before LZ4, sent as control messages) might not fit one.
        let mut block = self.opts.occlusion_block.max(1);
        while block <= occlusion::MAX_BLOCK
            && occlusion::max_encoded_len(BlockGrid::new(width, height, block).len()) + 1024
                > wire::MAX_META as usize
        {
            block += 1;
        }
        let grid = BlockGrid::new(width, height, block);
        // (One worker has nothing in front of it.)
        let occlusion = self.opts.occlusion
            && slots.len() > 1
            && matches!(source, FrameSource::Render)
            && block <= occlusion::MAX_BLOCK;
        // Without a prediction from the last frame for some worker, all take one from a
        // first pass at 1/PREPASS_SCALE of the resolution.
        let wall = match &self.wall {
            Some(j) => Some(j.frame(&slots).map_err(Failure::of)?),
            None => None,
        };
        // (A wall's stacked tiles are not a picture a low-resolution pass could stand for.)
        // (Nor for a frame whose first-pass map, one block per pixel at 1/PREPASS_SCALE,
        // might not fit a control message: its workers start without a prediction.)
        let pre_fits = occlusion::max_encoded_len(
            BlockGrid::new(
                width.div_ceil(PREPASS_SCALE),
                height.div_ceil(PREPASS_SCALE),
                1,
            )
            .len(),
        ) + 1024
            <= wire::MAX_META as usize;
        let prepass = occlusion
            && wall.is_none()
            && pre_fits
            && self.opts.occlusion_prepass
            && !self.occlusion_last.as_ref().is_some_and(|(w, h, last, _)| {
                (*w, *h) == (width, height) && same_fronts(last, &order)
            });
        // How far the scene moved on screen since the frame the workers predict from. Not
        // for a wall's frames: their image is the tiles stacked, so neither a plain view's
        // motion nor a dilation that crosses from one tile into the next fits them.
        let motion = match &self.occlusion_last {
            Some((.., last))
                if occlusion && !prepass && wall.is_none() && self.opts.occlusion_motion =>
            {
                let view = |c: &Camera| View::new(c, &self.render, width, height).ok();
                match (view(last), view(camera)) {
                    (Some(a), Some(b)) => {
                        let m = screen_motion(&a, &b, &self.costs.root, MOTION_QUANTILE);
                        m.ceil().min(width.max(height) as f64) as u32
                    }
                    _ => 0,
                }
            }
            _ => 0,
        };
        if motion > 0 {
            debug!(frame, motion_px = motion, "occlusion prediction widened");
        }
        let pre_grid = BlockGrid::new(
            width.div_ceil(PREPASS_SCALE),
            height.div_ceil(PREPASS_SCALE),
            1,
        );
        let mut pre_coverage: Vec<Option<Transmittance>> = vec![None; self.workers.len()];
        // The accumulators are as large as their grids (a 2^31-pixel wall's main grid has
        // hundreds of millions of blocks): one that the frame does not use is empty.
        let unused = BlockGrid::new(0, 0, 1);
        let mut pre_front = FrontAccumulator::new(if prepass { pre_grid } else { unused });
        let has_prepass = prepass;
        let mut pre_sent = !prepass;
        // Cross-worker occlusion: each worker's block transmittance, by rank. Each position
        // of the order gets its map as soon as the workers in front of it have reported.
        let mut coverage: Vec<Option<Transmittance>> = vec![None; self.workers.len()];
        let mut front = FrontAccumulator::new(if occlusion { grid } else { unused });
        let mut maps_sent = !occlusion;
        let mut occlusion_s = 0.0;
        // Workers on this host write their final spans into a canvas, in place.
        let mut canvas = if wall.is_none()
            && slots
                .iter()
                .any(|&r| self.workers[r as usize].shm.is_some())
        {
            self.take_canvas(width, height)
        } else {
            None
        };
        let canvas_ref = canvas.as_ref().map(|c| {
            let id = c.id();
            wire::CanvasRef {
                name: id.name,
                pid: id.pid,
                fd: id.fd,
            }
        });
        // Compositing is timed from here: the canvas (mapped in full when it is made, tens
        // of MB on a frame's first use) is not compositing.
        let t_sent = Instant::now();
        for (slot, &rank) in slots.iter().enumerate() {
            let mine = self.decomposition.worker_leaves(slot);
            let leaf_order = self
                .decomposition
                .leaf_order_of(slot, camera.eye)
                .into_iter()
                .map(|l| mine.iter().position(|&m| m == l).unwrap() as u32)
                .collect();
            let req = CoordMsg::Frame(FrameRequest {
                frame,
                camera: camera.clone(),
                width,
                height,
                order: order.clone(),
                leaf_order,
                composite: composite.clone(),
                source: source.clone(),
                leaves: self.new_leaves[rank as usize].take(),
                occlusion_block: if occlusion { block } else { 0 },
                occlusion_prepass: if prepass { PREPASS_SCALE } else { 0 },
                occlusion_motion: motion,
                page_work: self.wants_page_work(),
                wall: wall.clone(),
                canvas: canvas_ref
                    .clone()
                    .filter(|_| self.workers[rank as usize].shm.is_some()),
            });
            let w = &mut self.workers[rank as usize];
            let what = w.describe();
            with_timeout(
                self.opts.frame_timeout,
                format!("sending frame {frame} to {what}"),
                write_frame(&mut w.send, &wire::encode_meta(&req), &[]),
            )
            .await
            .map_err(|e| Failure::blaming(anyhow!(e), rank))?;
        }
        let n = self.workers.len();
        let mut stats: Vec<Option<WorkerFrameStats>> = vec![None; n];
        let mut pieces: Vec<Option<Final>> = (0..n).map(|_| None).collect();
        let mut last_arrival = t_sent;
        let mut gather_bytes = 0u64;
        let mut collect_s = 0.0;
        let deadline = t0 + self.opts.frame_timeout;
        let missing = |stats: &Vec<Option<WorkerFrameStats>>| -> Vec<u32> {
            slots
                .iter()
                .copied()
                .filter(|&r| stats[r as usize].is_none())
                .collect()
        };
        while !missing(&stats).is_empty() {
            let Ok(ev) = self.next_event(deadline).await else {
                let waiting_on = occlusion_phase(pre_sent, maps_sent, &pre_coverage, &coverage);
                let late = late_ranks(&slots, &order, waiting_on, missing(&stats));
                return Err(Failure {
                    error: anyhow!(
                        "frame {frame}: no result from {} within {:.0} s (cluster.frame_timeout_s)",
                        self.list(late.iter().map(|&r| r as usize)),
                        self.opts.frame_timeout.as_secs_f64()
                    ),
                    lost: late,
                });
            };
            match ev {
                Event::Msg { rank, .. } | Event::Lost { rank, .. } if !slots.contains(&rank) => {
                    debug!(rank, "ignoring a worker given up on");
                }
                Event::Exited { child, status }
                    if !self.child_rank(child).is_some_and(|r| slots.contains(&r)) =>
                {
                    debug!(child, %status, "a worker given up on has exited");
                }
                Event::Msg {
                    rank, frame: mut f, ..
                } => {
                    let who = self.workers[rank as usize].describe();
                    let blame = |e: anyhow::Error| Failure::blaming(e, rank);
                    // What a FrameDone's stats must be, whichever way its final piece came.
                    let own_stats = |s: &WorkerFrameStats| -> Result<(), Failure> {
                        if s.rank != rank {
                            return Err(blame(anyhow!(
                                "{who} sent the frame stats of rank {} as its own",
                                s.rank
                            )));
                        }
                        s.check_times().map_err(|e| {
                            blame(anyhow!("{who} sent frame {frame}'s stats with {e}"))
                        })
                    };
                    match wire::decode_meta::<WorkerMsg>(&f.meta) {
                        // Leftovers of an earlier (failed) frame are not this frame's.
                        Ok(WorkerMsg::FrameDone { frame: fno, .. })
                        | Ok(WorkerMsg::Coverage { frame: fno, .. })
                        | Ok(WorkerMsg::Failed {
                            frame: Some(fno), ..
                        }) if fno < frame => {
                            debug!(%who, fno, "ignoring a message of an earlier frame");
                        }
                        Ok(WorkerMsg::FrameDone {
                            frame: fno,
                            stats: s,
                            canvas: Some(span),
                            shm,
                            lz4,
                        }) if fno == frame && stats[rank as usize].is_none() => {
                            own_stats(&s)?;
                            if canvas.is_none() || self.workers[rank as usize].shm.is_none() {
                                return Err(blame(anyhow!(
                                    "{who} wrote its final piece into a canvas it was not given"
                                )));
                            }
                            if shm.is_some() || lz4 || !f.bulk.is_empty() {
                                return Err(blame(anyhow!(
                                    "{who} sent a final piece besides the one it wrote into the canvas"
                                )));
                            }
                            if span.start > span.end || span.end as u64 > pixels {
                                return Err(blame(anyhow!(
                                    "{who} reports writing pixels {span} into the canvas of a {width}x{height} frame"
                                )));
                            }
                            gather_bytes += f.wire_len() + span.len() as u64 * PIXEL_BYTES;
                            last_arrival = Instant::now();
                            pieces[rank as usize] = Some(Final::InCanvas(span));
                            stats[rank as usize] = Some(s);
                        }
                        Ok(WorkerMsg::FrameDone {
                            frame: fno,
                            stats: s,
                            shm,
                            lz4,
                            canvas: None,
                        }) if fno == frame && stats[rank as usize].is_none() => {
                            own_stats(&s)?;
                            if lz4 && !composite.lz4 {
                                return Err(blame(anyhow!(
                                    "{who} sent a compressed final piece, in a run without composite.lz4"
                                )));
                            }
                            let t = Instant::now();
                            gather_bytes += f.wire_len();
                            let limit = self.piece_limit();
                            let piece = match (shm, &mut self.workers[rank as usize].shm) {
                                (None, _) => tokio::task::block_in_place(|| {
                                    if lz4 {
                                        SparsePiece::parse_lz4(&f.bulk, width * height)
                                    } else {
                                        let bulk = std::mem::take(&mut f.bulk);
                                        SparsePiece::parse_shared(bulk.into(), width * height)
                                    }
                                })
                                .with_context(|| format!("final piece from {who}"))
                                .map_err(blame)?,
                                (Some(_), _) if lz4 => {
                                    return Err(blame(anyhow!(
                                        "{who} announced a compressed final piece in shared memory, which never holds one"
                                    )))
                                }
                                (Some(at), Some(r)) => {
                                    if !f.bulk.is_empty() {
                                        return Err(blame(anyhow!(
                                            "{who} sent its final piece both inline and in shared memory"
                                        )));
                                    }
                                    let piece = tokio::task::block_in_place(|| {
                                        r.read_piece(
                                            at,
                                            limit,
                                            frame,
                                            wire::GATHER_ROUND,
                                            rank,
                                            width * height,
                                        )
                                    })
                                    .with_context(|| {
                                        format!("the final piece of {who} in shared memory")
                                    })
                                    .map_err(blame)?;
                                    // Counted once the record's length has been checked.
                                    gather_bytes += wire::SHM_RECORD_HEADER as u64 + at.len;
                                    piece
                                }
                                (Some(_), None) => {
                                    return Err(blame(anyhow!(
                                        "{who} announced its final piece in shared memory, which it was not given"
                                    )))
                                }
                            };
                            last_arrival = Instant::now();
                            pieces[rank as usize] = Some(Final::Piece(piece));
                            stats[rank as usize] = Some(s);
                            collect_s += t.elapsed().as_secs_f64();
                        }
                        // Coverage of the first pass or of the frame: each position's map goes
                        // out once the workers in front of it have sent theirs.
                        Ok(WorkerMsg::Coverage {
                            frame: fno,
                            rect,
                            prepass,
                        }) if fno == frame
                            && if prepass {
                                has_prepass && pre_coverage[rank as usize].is_none()
                            } else {
                                // (A worker whose first-pass map came may send this before
                                // the first pass of the workers behind it is done.)
                                occlusion && coverage[rank as usize].is_none()
                            } =>
                        {
                            let t = Instant::now();
                            let (g, cov, acc, what) = if prepass {
                                (
                                    pre_grid,
                                    &mut pre_coverage,
                                    &mut pre_front,
                                    "first-pass coverage",
                                )
                            } else {
                                (grid, &mut coverage, &mut front, "occlusion coverage")
                            };
                            let map = Transmittance::decoded(g, rect, &f.bulk)
                                .with_context(|| format!("{what} from {who}"))
                                .map_err(blame)?;
                            cov[rank as usize] = Some(map);
                            // Every position whose front has now reported gets its map (the
                            // first has nothing in front and gets none). The folds go in
                            // order; the maps they give are encoded in parallel: when the
                            // slowest worker in front reports, the maps of all the positions
                            // behind it are due at once, and one after the other they took
                            // about 1.4 ms each on 16 cores (docs/BENCHMARKS.md).
                            let encode = |(to, map): (u32, occlusion::FrontTransmittance)| {
                                (to, occlusion::encode_levels(&map.q))
                            };
                            let encoded: Vec<(u32, Vec<u8>)> = tokio::task::block_in_place(|| {
                                let mut due = Vec::new();
                                while acc.folded() + 1 < order.len() {
                                    let Some(layer) = cov[order[acc.folded()] as usize].as_ref()
                                    else {
                                        break;
                                    };
                                    let map = acc.fold(layer);
                                    due.push((order[acc.folded()], map));
                                }
                                if due.len() > 1 {
                                    due.into_par_iter().map(encode).collect()
                                } else {
                                    due.into_iter().map(encode).collect()
                                }
                            });
                            for (to, bytes) in encoded {
                                self.send_occlusion(frame, to, bytes, deadline, prepass)
                                    .await
                                    .map_err(|(e, r)| Failure::blaming(e, r))?;
                            }
                            if acc.folded() + 1 >= order.len() {
                                if prepass {
                                    pre_sent = true;
                                } else if !maps_sent {
                                    maps_sent = true;
                                    self.occlusion_last =
                                        Some((width, height, order.clone(), camera.clone()));
                                }
                            }
                            occlusion_s += t.elapsed().as_secs_f64();
                        }
                        Ok(WorkerMsg::Failed {
                            message, suspects, ..
                        }) => {
                            // A worker that failed because peers vanished or stalled blames
                            // them; only ranks of this frame count, each once, and not
                            // those only waiting for an occlusion map.
                            let waiting_on =
                                occlusion_phase(pre_sent, maps_sent, &pre_coverage, &coverage);
                            let lost = narrow_suspects(suspects, &slots, &order, rank, waiting_on);
                            return Err(Failure {
                                error: anyhow!("frame {frame} failed on {who}: {message}"),
                                lost,
                            });
                        }
                        Ok(other) => {
                            return Err(Failure::of(anyhow!(
                                "{who} sent {other:?} during frame {frame}"
                            )))
                        }
                        Err(e) => {
                            return Err(Failure::of(anyhow!("{who} sent a malformed message: {e}")))
                        }
                    }
                }
                ev => {
                    let lost = match &ev {
                        Event::Lost { rank, .. } => vec![*rank],
                        Event::Exited { child, .. } => {
                            self.child_rank(*child).into_iter().collect()
                        }
                        Event::Msg { .. } => vec![],
                    };
                    return Err(Failure {
                        error: self.event_error(ev).context(format!("frame {frame}")),
                        lost,
                    });
                }
            }
        }
        let stats: Vec<WorkerFrameStats> = slots
            .iter()
            .map(|&r| stats[r as usize].take().unwrap())
            .collect();
        let pieces: Vec<Final> = slots
            .iter()
            .map(|&r| pieces[r as usize].take().unwrap())
            .collect();
        if wall.is_none() {
            let spans: Vec<Span> = pieces
                .iter()
                .map(|p| match p {
                    Final::Piece(p) => p.span,
                    Final::InCanvas(s) => *s,
                })
                .collect();
            final_spans_match_the_plan(width * height, composite, &order, &slots, &spans).map_err(
                |(rank, e)| {
                    Failure::blaming(
                        e.context(format!(
                            "frame {frame}: {}",
                            self.workers[rank as usize].describe()
                        )),
                        rank,
                    )
                },
            )?;
        }
        let canvas_blended = stats.iter().filter(|s| s.blended_in_canvas).count();
        let pieces_in_canvas = pieces
            .iter()
            .filter(|p| matches!(p, Final::InCanvas(_)))
            .count();
        let t = Instant::now();
        let image = match &wall {
            // Tiles were written by their drivers: check each wrote all of its own.
            Some(w) => {
                for s in &stats {
                    let want = w.drivers.iter().filter(|&&d| d == s.rank).count() as u32;
                    if s.tiles_written != want {
                        return Err(Failure::of(anyhow!(
                            "frame {frame}: {} drives {want} wall tiles but wrote {}",
                            self.workers[s.rank as usize].describe(),
                            s.tiles_written
                        )));
                    }
                }
                for p in &pieces {
                    let span = match p {
                        Final::Piece(p) => p.span,
                        Final::InCanvas(s) => *s,
                    };
                    if !span.is_empty() {
                        return Err(Failure::of(anyhow!(
                            "frame {frame}: a wall frame's final piece holds pixels {span}"
                        )));
                    }
                }
                FrameImage::Owned(Vec::new())
            }
            None => {
                let interlace =
                    Interlace::new(width, height, slots.len() as u32, composite.interlace);
                match canvas.take() {
                    Some(mut c) => {
                        tokio::task::block_in_place(|| finish_canvas(&mut c, &interlace, &pieces))
                            .map_err(|e| Failure::of(e.into()))?;
                        let c = Arc::new(c);
                        self.canvases.push(c.clone());
                        FrameImage::Canvas(c)
                    }
                    None => {
                        let pieces: Vec<SparsePiece> = pieces
                            .into_iter()
                            .map(|p| match p {
                                Final::Piece(p) => Ok(p),
                                Final::InCanvas(_) => {
                                    Err(Failure::of(anyhow!("a canvas piece without a canvas")))
                                }
                            })
                            .collect::<Result<_, _>>()?;
                        FrameImage::Owned(
                            tokio::task::block_in_place(|| {
                                assemble(width, height, &interlace, &pieces)
                            })
                            .map_err(|e| Failure::of(e.into()))?,
                        )
                    }
                }
            }
        };
        let assemble_s = t.elapsed().as_secs_f64();
        // Rendering includes waiting for the occlusion maps and the fix-up render.
        let slowest_render = stats
            .iter()
            .map(|s| s.render_s + s.prepass_s + s.occlusion_s + s.fixup_s)
            .fold(0.0, f64::max);
        Ok(FrameResult {
            image,
            composite_s: ((last_arrival - t_sent).as_secs_f64() - slowest_render).max(0.0),
            stats,
            wall_s: t0.elapsed().as_secs_f64(),
            gather_bytes,
            canvas_gather: pieces_in_canvas,
            canvas_blended,
            collect_s,
            assemble_s,
            lost: Vec::new(),
            joined: Vec::new(),
            occlusion_s,
        })
    }

    /// Sends worker `rank` its occlusion map of the frame (the transmittance of what the
    /// workers in front of it hold, per block, as `occlusion::encode_levels` bytes).
    async fn send_occlusion(
        &mut self,
        frame: u64,
        rank: u32,
        front: Vec<u8>,
        deadline: Instant,
        prepass: bool,
    ) -> Result<(), (anyhow::Error, u32)> {
        let w = &mut self.workers[rank as usize];
        let what = w.describe();
        let msg = wire::encode_meta(&CoordMsg::Occlusion {
            frame,
            front,
            prepass,
        });
        with_timeout(
            deadline.saturating_duration_since(Instant::now()),
            format!("sending the occlusion map of frame {frame} to {what}"),
            write_frame(&mut w.send, &msg, &[]),
        )
        .await
        .map(drop)
        .map_err(|e| (anyhow!(e), rank))
    }

    /// Kills the spawned worker process `pid` (none if this process did not spawn it).
    fn kill_child(&self, pid: u32) {
        // The latest child with the pid: an earlier one that exited may share it.
        if let Some(c) = self.children.iter().rfind(|c| c.pid == pid) {
            c.kill.kill();
        }
    }

    /// The rank of local worker process `child`, if it joined.
    fn child_rank(&self, child: usize) -> Option<u32> {
        let pid = self.children.get(child)?.pid;
        self.workers.iter().find(|w| w.pid == pid).map(|w| w.rank)
    }

    /// Whether frame requests ask the workers where their time went, page by page: a
    /// re-split by measured pages may follow.
    fn wants_page_work(&self) -> bool {
        self.opts.rebalance_threshold > 0.0
            && self.opts.rebalance_model == RebalanceModel::Pages
            && self.slots.len() >= 2
    }

    /// After a frame of a sequence: when the workers' measured imbalance exceeds
    /// `cluster.rebalance_threshold`, re-splits the tree from the measured per-leaf times
    /// (damped by `cluster.rebalance_damping`; with `cluster.rebalance_model = "pages"`,
    /// each leaf's time divided among the pages its rays entered, when the workers reported
    /// any) and hands each worker its new leaves with the next frame. The workers keep their
    /// engines and resident pages.
    pub fn rebalance(&mut self, done: &FrameResult, frame: u64) -> Option<Rebalance> {
        let t = self.opts.rebalance_threshold;
        if t <= 0.0 || self.slots.len() < 2 || !done.lost.is_empty() {
            return None;
        }
        let d = &self.decomposition;
        // The stats are in slot order (the decomposition's workers).
        let (measured, clock) =
            decompose::measured_leaf_times(d, &done.stats, self.opts.rebalance_clock);
        let imbalance = d.measured_imbalance(&measured);
        if !(imbalance > t) {
            return None;
        }
        // Where each leaf's time went, page by page (`(leaf, key, share)`). A worker sends at
        // most `MAX_PAGE_WORK` records; more (a faulty peer) are not read.
        let mut work = Vec::new();
        for (slot, s) in done.stats.iter().enumerate() {
            let mine = d.worker_leaves(slot);
            for w in s.page_work.iter().take(wire::MAX_PAGE_WORK) {
                if let Some(&l) = mine.get(w.leaf as usize) {
                    work.push((l, w.key, w.share));
                }
            }
        }
        let by_pages = self.opts.rebalance_model == RebalanceModel::Pages && !work.is_empty();
        if !by_pages {
            work.clear();
        }
        // The field is kept only with the split it gives: the next re-split compares its
        // measurement with the costs of the leaves in force, which were computed from the
        // field in force (a field re-weighted again and again under unchanged leaves
        // compounds the correction past the damping).
        let Some(decompose::Resplit {
            decomposition: new,
            field: boxes,
            expected_imbalance,
        }) = decompose::resplit(
            &self.estimate,
            &self.costs,
            d,
            &decompose::Measurement {
                times: &measured,
                work: &work,
            },
            self.opts.rebalance_damping,
            self.slots.len(),
            self.opts.leaves_per_worker,
        )
        else {
            // The split planes snapped back to the same brick boundaries, damped and not,
            // or the new split would gain too little: nothing to send, and the field in
            // force stays.
            debug!(frame, "re-split leaves the regions as they are");
            return None;
        };
        self.costs.boxes = boxes;
        let r = Rebalance {
            after_frame: frame,
            measured_imbalance: imbalance,
            expected_imbalance,
            model: if by_pages { "pages" } else { "leaves" },
            page_records: if by_pages { work.len() } else { 0 },
            clock,
            old_leaves: d.tree.leaves.clone(),
            new_leaves: new.tree.leaves.clone(),
        };
        info!(
            frame,
            measured = format!("{imbalance:.3}"),
            expected = format!("{:.3}", r.expected_imbalance),
            model = r.model,
            clock = r.clock,
            "re-split the k-d tree from measured render times"
        );
        for (slot, &rank) in self.slots.iter().enumerate() {
            let leaves = new.worker_leaves(slot);
            self.new_leaves[rank as usize] =
                Some(leaves.iter().map(|&l| new.tree.leaves[l]).collect());
        }
        self.decomposition = new;
        Some(r)
    }

    /// Tells every worker to exit and waits (briefly) for them. A local worker that does
    /// not exit is killed when the task waiting on its process ends with the runtime
    /// (`kill_on_drop`), or when this process exits (`PR_SET_PDEATHSIG`): not when the
    /// cluster is dropped.
    pub async fn shutdown(mut self) {
        // Replacements spawned and never admitted have no part in the run to finish.
        for &pid in &self.respawned {
            self.kill_child(pid);
        }
        let slots = self.slots.clone();
        for w in self.workers.iter_mut().filter(|w| slots.contains(&w.rank)) {
            let _ = tokio::time::timeout(
                Duration::from_secs(2),
                write_frame(&mut w.send, &wire::encode_meta(&CoordMsg::Shutdown), &[]),
            )
            .await;
            let _ = w.send.finish();
        }
        if !self.children.is_empty() {
            let deadline = Instant::now() + Duration::from_secs(5);
            // Only the workers still in the run (lost ones were killed already).
            let alive =
                |this: &Self, c: usize| this.child_rank(c).is_some_and(|r| slots.contains(&r));
            let expected = (0..self.children.len())
                .filter(|&c| alive(&self, c))
                .count();
            let mut exited = 0;
            while exited < expected {
                match self.next_event(deadline).await {
                    Ok(Event::Exited { child, .. }) if alive(&self, child) => exited += 1,
                    Ok(_) => {}
                    Err(()) => break,
                }
            }
        }
        // Let each worker read the shutdown and close first, so none mistakes our close
        // for a lost coordinator.
        let deadline = Instant::now() + Duration::from_secs(3);
        for w in &self.workers {
            let left = deadline.saturating_duration_since(Instant::now());
            let _ = tokio::time::timeout(left, w.conn.closed()).await;
            w.conn.close(0u32.into(), b"done");
        }
        let _ = tokio::time::timeout(Duration::from_secs(1), self.ep.wait_idle()).await;
    }
}

/// An error in the set-up of `rank`: a newcomer (`fresh`) is given up on (pushed to `lost`),
/// anyone else's ends the run.
fn give_up_fresh(
    fresh: &[u32],
    rank: u32,
    e: anyhow::Error,
    lost: &mut Vec<(u32, String)>,
) -> Result<()> {
    if fresh.contains(&rank) {
        lost.push((rank, format!("{e:#}")));
        Ok(())
    } else {
        Err(e)
    }
}

/// Tells an authenticated worker that the run is full and closes its connection.
async fn refuse_full(j: Authenticated, n: usize) {
    let (name, pid, _, _, conn, mut send, _) = j;
    warn!(%name, pid, "refused a worker: the run already has {n}");
    let msg = wire::encode_meta(&CoordMsg::Refused {
        reason: format!("the run already has its {n} workers"),
    });
    let _ = tokio::time::timeout(Duration::from_secs(1), write_frame(&mut send, &msg, &[])).await;
    let _ = send.finish();
    conn.close(6u32.into(), b"run is full");
}

type Authenticated = (
    String,
    u32,
    wire::Fingerprint,
    Option<String>,
    quinn::Connection,
    quinn::SendStream,
    quinn::RecvStream,
);

/// Completes the handshake of one connection: the first frame must be a `Hello` with the
/// run's secret; anything else is refused, logged and closed.
///
/// The whole of it has one 10 s deadline (not 10 s per step): a connection holds one of
/// the listener's handshake permits until it is done, and a stranger that dawdles through
/// each step could otherwise hold one for 30 s. (A worker turned away for want of a permit
/// tries again, `transport::connect_until`.)
async fn authenticate(incoming: quinn::Incoming, secret: &[u8]) -> Result<Authenticated> {
    let deadline = Instant::now() + Duration::from_secs(10);
    let left = || deadline.saturating_duration_since(Instant::now());
    let conn = with_timeout(left(), "QUIC handshake", incoming.into_future()).await?;
    let (mut send, mut recv) =
        with_timeout(left(), "opening the control stream", conn.accept_bi()).await?;
    let f = match with_timeout(
        left(),
        "the hello",
        read_frame(&mut recv, &Limits::HANDSHAKE),
    )
    .await
    {
        Ok(f) => f,
        Err(e) => {
            conn.close(4u32.into(), b"bad hello");
            return Err(anyhow!("{e}"));
        }
    };
    match wire::decode_meta::<WorkerMsg>(&f.meta) {
        Ok(WorkerMsg::Hello {
            secret: s,
            name,
            pid,
            fingerprint,
            host,
        }) => {
            if !secret::ct_eq(&s.0, secret) {
                let msg = wire::encode_meta(&CoordMsg::Refused {
                    reason: "wrong shared secret".into(),
                });
                let _ = tokio::time::timeout(left(), write_frame(&mut send, &msg, &[])).await;
                let _ = send.finish();
                tokio::time::sleep(Duration::from_millis(50)).await;
                conn.close(5u32.into(), b"wrong secret");
                bail!("worker {name:?} (pid {pid}) presented the wrong shared secret");
            }
            // The fingerprint goes to every peer, which accepts only this certificate for
            // this worker's rank: a hello naming another than the one presented would break
            // the mesh.
            let presented = tls::peer_fingerprint(&conn);
            if !presented.is_some_and(|p| secret::ct_eq(&p, &fingerprint)) {
                let reason = format!(
                    "the certificate presented ({}) is not the one the hello names ({})",
                    presented.map_or("none".into(), |p| tls::to_hex(&p)),
                    tls::to_hex(&fingerprint)
                );
                let msg = wire::encode_meta(&CoordMsg::Refused {
                    reason: reason.clone(),
                });
                let _ = tokio::time::timeout(left(), write_frame(&mut send, &msg, &[])).await;
                let _ = send.finish();
                tokio::time::sleep(Duration::from_millis(50)).await;
                conn.close(5u32.into(), b"wrong certificate");
                bail!("worker {name:?} (pid {pid}): {reason}");
            }
            Ok((name, pid, fingerprint, host, conn, send, recv))
        }
        Ok(other) => {
            conn.close(4u32.into(), b"expected hello");
            bail!("expected a hello, got {other:?}")
        }
        Err(e) => {
            conn.close(4u32.into(), b"malformed hello");
            bail!("malformed hello: {e}")
        }
    }
}

/// Forwards a worker's control messages as events; a malformed frame closes that
/// worker's connection (and only that one), and so does a worker silent for `silence`
/// ([`spawn_watchdog`]).
fn spawn_reader(
    rank: u32,
    conn: quinn::Connection,
    mut recv: quinn::RecvStream,
    limits: Limits,
    tx: mpsc::UnboundedSender<Event>,
    silence: Duration,
) {
    spawn_watchdog(conn.clone(), silence);
    // The messages of this worker waiting to be handled hold at most two of the largest
    // it may send (in KiB): past that the reader stops reading, and QUIC's flow control
    // stops the worker, instead of a flood of (stale) messages queueing without bound.
    let kib = |bytes: u64| bytes.div_ceil(1024).clamp(1, u32::MAX as u64 / 2) as u32;
    let largest = kib(limits.max_meta as u64 + limits.max_bulk + wire::HEADER_LEN as u64);
    let budget = Arc::new(tokio::sync::Semaphore::new(2 * largest as usize));
    tokio::spawn(async move {
        loop {
            match read_frame(&mut recv, &limits).await {
                Ok(frame) => {
                    let need = kib(frame.wire_len()).min(largest);
                    let Ok(held) = budget.clone().acquire_many_owned(need).await else {
                        return;
                    };
                    if tx
                        .send(Event::Msg {
                            rank,
                            frame,
                            _held: held,
                        })
                        .is_err()
                    {
                        return;
                    }
                }
                Err(e) => {
                    if matches!(e, NetError::Wire(_)) {
                        conn.close(4u32.into(), b"malformed frame");
                    }
                    let _ = tx.send(Event::Lost {
                        rank,
                        error: e.to_string(),
                    });
                    return;
                }
            }
        }
    });
}

/// Closes `conn` once nothing (no datagram at all) has come from the worker for
/// `silence`, the run's idle timeout, so that a hung worker (stopped, or its host gone) is
/// given up after that long whatever the load. Both sides send keep-alives at half the idle
/// timeout, so a live worker's connection is never that quiet. QUIC's own idle timeout
/// waits for at least three probe timeouts, which on a loaded machine (inflated round-trip
/// estimates) stretched detection to 2.9 s of a 2 s timeout (`bench-soak` at 1280×720).
/// The reader then reports the worker lost, as for any closed connection.
fn spawn_watchdog(conn: quinn::Connection, silence: Duration) {
    tokio::spawn(async move {
        let tick = (silence / 40).clamp(Duration::from_millis(5), Duration::from_millis(50));
        let mut seen = conn.stats().udp_rx.datagrams;
        let mut heard = Instant::now();
        loop {
            tokio::select! {
                _ = conn.closed() => return,
                _ = tokio::time::sleep(tick) => {}
            }
            let now = conn.stats().udp_rx.datagrams;
            if now != seen {
                seen = now;
                heard = Instant::now();
            } else if heard.elapsed() >= silence {
                warn!(
                    silent_s = format!("{:.2}", heard.elapsed().as_secs_f64()),
                    "a worker has sent nothing for the idle timeout; closing its connection"
                );
                conn.close(8u32.into(), b"silent for the idle timeout");
                return;
            }
        }
    });
}

/// Whether process `pid` exists (a child of ours that exited is reaped at once by its
/// wait task, so a dead one is gone).
fn process_alive(pid: u32) -> bool {
    // SAFETY: signal 0 only checks that the process exists.
    pid != 0 && unsafe { libc::kill(pid as i32, 0) } == 0
}

/// How this coordinator starts its local worker processes (local mode), kept for the
/// whole run so that lost ones can be replaced (`cluster.respawn`).
struct Spawner {
    exe: PathBuf,
    args: Vec<String>,
    connect: SocketAddr,
    fingerprint: String,
    secret: Vec<u8>,
    idle_timeout: Duration,
    connect_timeout: Duration,
    quic_mtu: u16,
    /// Rayon threads per worker.
    threads: usize,
    /// `cluster.pin_workers`: the allowed CPUs in topology order, cut into one block per
    /// worker slot ([`strata_worker::affinity::block_for`]), and the run's worker count.
    pin: Option<(Vec<usize>, usize)>,
}

impl Spawner {
    fn new(
        opts: &ClusterOptions,
        workers: usize,
        connect: SocketAddr,
        fingerprint: &str,
        secret: &[u8],
    ) -> Result<Spawner> {
        let (exe, args) = match &opts.worker_exe {
            Some(p) => (p.clone(), vec![]),
            None => (
                std::env::current_exe().context("locating this executable to spawn workers")?,
                vec!["worker".to_string()],
            ),
        };
        let pin_order = match (opts.pin_workers, affinity::allowed()) {
            (false, _) => None,
            (true, Some(cpus)) => Some(affinity::topology_order(&cpus, affinity::place_of)),
            (true, None) => {
                warn!("cluster.pin_workers: this system does not say which CPUs may be used; the workers run unbound");
                None
            }
        };
        let threads = if opts.worker_threads > 0 {
            opts.worker_threads
        } else if let Some(order) = &pin_order {
            // Bound: as many threads as each worker has CPUs of its own.
            (order.len() / workers.max(1)).max(1)
        } else {
            let cores = std::thread::available_parallelism().map_or(1, |c| c.get());
            cores.div_ceil(workers.max(1)).max(1)
        };
        Ok(Spawner {
            exe,
            args,
            connect,
            fingerprint: fingerprint.to_string(),
            secret: secret.to_vec(),
            idle_timeout: opts.idle_timeout,
            connect_timeout: opts.connect_timeout,
            quic_mtu: opts.quic_mtu,
            threads,
            pin: pin_order.map(|order| {
                if workers > order.len() {
                    warn!(
                        workers,
                        cpus = order.len(),
                        "cluster.pin_workers: more workers than CPUs; each is bound to one CPU that others share"
                    );
                }
                (order, workers)
            }),
        })
    }

    /// Starts local worker process number `child` (named `local-{child}`, on GPU slot
    /// `gpu`), which dials this coordinator; its exit is reported on `tx` as
    /// [`Event::Exited`]. Returns its pid.
    ///
    /// With `cluster.pin_workers` it is bound to the CPUs of slot `gpu` (the slot of the
    /// worker a replacement replaces).
    fn spawn(
        &self,
        child: usize,
        gpu: usize,
        tx: &mpsc::UnboundedSender<Event>,
    ) -> Result<(u32, ChildKill)> {
        let cpus = self
            .pin
            .as_ref()
            .map(|(order, workers)| affinity::block_for(order, *workers, self.threads, gpu).0);
        let mut cmd = tokio::process::Command::new(&self.exe);
        cmd.args(&self.args)
            .arg("--connect")
            .arg(self.connect.to_string())
            .arg("--fingerprint")
            .arg(&self.fingerprint)
            .arg("--name")
            .arg(format!("local-{child}"))
            .arg("--bind")
            .arg(format!("{}:0", self.connect.ip()))
            .arg("--idle-timeout-s")
            .arg(self.idle_timeout.as_secs_f64().to_string())
            .arg("--connect-timeout-s")
            .arg(self.connect_timeout.as_secs_f64().to_string())
            .arg("--quic-mtu")
            .arg(self.quic_mtu.to_string())
            .env(
                secret::SECRET_ENV,
                std::ffi::OsString::from_vec(self.secret.clone()),
            )
            .env("RAYON_NUM_THREADS", self.threads.to_string())
            // Spread GPU workers over the node's GPUs (one each while there are enough).
            .env(strata_worker::gpu::GPU_SLOT_ENV, gpu.to_string())
            .stdin(Stdio::null())
            .kill_on_drop(true);
        // The workers die with the coordinator, however it ends (even SIGKILL). A bound
        // worker's threads inherit its binding from the first. PR_SET_PDEATHSIG fires when
        // the *thread* that forked the child ends, so `spawn` (and a respawn) must run on a
        // thread that lives as long as the run: the `Cluster`'s futures are driven by
        // `block_on` on the calling thread (`render::render_distributed`), never from
        // `spawn_blocking`, whose idle threads exit after 10 s.
        let set = cpus.as_deref().map(affinity::CpuSet::new);
        unsafe {
            cmd.pre_exec(move || {
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                if let Some(set) = &set {
                    set.bind()?;
                }
                Ok(())
            });
        }
        let mut proc = cmd
            .spawn()
            .with_context(|| format!("cannot start worker {}", self.exe.display()))?;
        let pid = proc.id().unwrap_or(0);
        if let Some(c) = &cpus {
            let mut c = c.clone();
            c.sort_unstable();
            debug!(child, pid, cpus = %affinity::format_list(&c), "bound a worker to its CPUs");
        }
        let tx = tx.clone();
        let kill = ChildKill(Arc::new(tokio::sync::Notify::new()));
        let asked = kill.0.clone();
        tokio::spawn(async move {
            let status = tokio::select! {
                s = proc.wait() => s,
                // (Until `wait` has returned, the child is not reaped: its pid is its own,
                // if only as a zombie.)
                () = asked.notified() => {
                    let _ = proc.start_kill();
                    proc.wait().await
                }
            };
            let status = match status {
                Ok(s) => describe_status(s),
                Err(e) => e.to_string(),
            };
            let _ = tx.send(Event::Exited { child, status });
        });
        Ok((pid, kill))
    }
}

/// Kills one spawned worker process through the task that owns its handle
/// ([`Spawner::spawn`]): a request made after the child was reaped does nothing.
#[derive(Clone)]
struct ChildKill(Arc<tokio::sync::Notify>);

/// A worker process this process spawned.
struct SpawnedChild {
    /// Its process id (what its hello reports).
    pid: u32,
    /// Kills it through its own process handle, which does nothing once the child has been
    /// reaped. A bare `kill(pid)` after the child exited and was reaped could hit an
    /// unrelated process that reused the pid.
    kill: ChildKill,
    /// Its GPU slot (`GPU_SLOT_ENV`; a replacement takes the slot of the worker it replaces).
    gpu: usize,
}

impl ChildKill {
    fn kill(&self) {
        // A stored permit: the request holds even before the task first waits.
        self.0.notify_one();
    }
}

fn describe_status(s: std::process::ExitStatus) -> String {
    use std::os::unix::process::ExitStatusExt;
    match (s.code(), s.signal()) {
        (Some(c), _) => format!("exit status {c}"),
        (None, Some(sig)) => format!("killed by signal {sig}"),
        _ => s.to_string(),
    }
}

#[cfg(test)]
mod watchdog_tests {
    use super::*;
    use strata_net::{Identity, NetConfig};

    /// A live peer keeps its connection; once its process stops answering (here: its only
    /// runtime thread blocked, as under SIGSTOP) the watchdog closes the connection after
    /// `silence`, long before QUIC's own idle timeout (30 s here) would.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_silent_peer_is_closed_after_the_silence_and_a_live_one_is_not() {
        let cfg = NetConfig {
            idle_timeout: Duration::from_secs(30),
            keep_alive: Duration::from_millis(200),
            ..NetConfig::default()
        };
        let id = Identity::generate().unwrap();
        let server = transport::endpoint("127.0.0.1:0".parse().unwrap(), &id, &cfg).unwrap();
        let addr = server.local_addr().unwrap();
        let (fp, peer_cfg) = (id.fingerprint, cfg.clone());
        let (ready_tx, ready_rx) = tokio::sync::oneshot::channel();
        let peer = std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .unwrap();
            rt.block_on(async move {
                let pid = Identity::generate().unwrap();
                let ep =
                    transport::endpoint("127.0.0.1:0".parse().unwrap(), &pid, &peer_cfg).unwrap();
                let conn = transport::connect(&ep, addr, fp, &peer_cfg, Duration::from_secs(5))
                    .await
                    .unwrap();
                ready_tx.send(()).unwrap();
                // Live for 2 s (its runtime answers keep-alives), then stopped for 4 s.
                tokio::time::sleep(Duration::from_secs(2)).await;
                std::thread::sleep(Duration::from_secs(4));
                drop(conn);
            });
        });
        let conn = server.accept().await.unwrap().await.unwrap();
        ready_rx.await.unwrap();
        let t = Instant::now();
        spawn_watchdog(conn.clone(), Duration::from_secs(1));
        tokio::time::sleep(Duration::from_millis(1800)).await;
        assert!(conn.close_reason().is_none(), "a live peer was closed");
        let e = conn.closed().await;
        let at = t.elapsed();
        assert!(
            matches!(e, quinn::ConnectionError::LocallyClosed),
            "{e:?} after {at:?}"
        );
        // Stopped at about 2 s, silent from its last datagram: closed about 1 s later.
        assert!(
            at >= Duration::from_millis(2500) && at < Duration::from_millis(4000),
            "closed after {at:?}"
        );
        peer.join().unwrap();
    }
}

#[cfg(test)]
mod blame_tests {
    use super::*;

    /// A worker's last compositing round still times out before the coordinator gives up on
    /// the frame, for any frame timeout and number of rounds: the rounds' staggered
    /// deadlines fit in the margin between the two timeouts.
    #[test]
    fn staggered_round_deadlines_end_before_the_coordinators() {
        for secs in [0.01, 1.0, 5.0, 30.0, 49.0, 50.0, 51.0, 120.0, 3600.0] {
            let coordinator = Duration::from_secs_f64(secs);
            let worker = worker_frame_timeout(coordinator);
            for rounds in [1usize, 2, 3, 5, 10, 17, 64] {
                let stagger = strata_common::composite::round_stagger(worker, rounds);
                let last = worker + stagger * (rounds as u32 - 1);
                assert!(
                    last < coordinator,
                    "{secs} s, {rounds} rounds: the last round ends at {last:?}"
                );
                // The stagger is at least half the margin spread over the rounds (it
                // separates reports by more than the network's delays).
                if rounds > 1 {
                    let margin = coordinator - worker;
                    assert!(
                        stagger * (2 * rounds as u32) + Duration::from_millis(1) >= margin,
                        "{secs} s, {rounds} rounds: {stagger:?} of {margin:?}"
                    );
                }
            }
        }
    }

    /// A worker's suspects while maps are going out: the healthy workers stuck waiting for
    /// their maps behind a hung one are not given up, the hung one is.
    #[test]
    fn suspects_waiting_for_a_map_are_not_blamed_for_it() {
        let (slots, order) = ([0u32, 1, 2, 3], [0u32, 2, 1, 3]);
        // Rank 2 (position 1) has not reported its coverage; 1 and 3 wait behind it.
        let c = cov(&[true, true, false, false]);
        // Rank 0 names 2, 1 and 3 (no pieces from any): only 2 is blamed.
        assert_eq!(
            narrow_suspects(vec![3, 1, 2, 1], &slots, &order, 0, Some(&c)),
            [2]
        );
        // Named without the one they wait on: that one is blamed instead.
        assert_eq!(
            narrow_suspects(vec![1, 3], &slots, &order, 0, Some(&c)),
            [2]
        );
        // Once every map went out, the suspects stand as named (each once, never itself).
        assert_eq!(
            narrow_suspects(vec![3, 1, 1, 0], &slots, &order, 0, None),
            [1, 3]
        );
        // A suspect in front of the missing coverage is kept (it had its map): rank 1 at
        // position 2 is missing, 2 (position 1) stays and 3 behind it goes.
        let c = cov(&[true, false, true, false]);
        assert_eq!(
            narrow_suspects(vec![2, 3], &slots, &order, 0, Some(&c)),
            [2]
        );
        // Every coverage in (the last sends none): no narrowing.
        let c = cov(&[true, true, true, false]);
        assert_eq!(
            narrow_suspects(vec![2, 3], &slots, &order, 0, Some(&c)),
            [2, 3]
        );
    }

    /// The gather refuses a worker whose final piece is not its part of the plan (an empty
    /// piece would have passed its checks and left a transparent stripe), for every
    /// algorithm and with the order not the rank order; the honest pieces pass.
    #[test]
    fn a_final_piece_that_is_not_the_workers_part_is_blamed_on_it() {
        use strata_common::composite::{Algorithm, WireFormat};
        let order = [2u32, 0, 1];
        let slots = [0u32, 1, 2];
        for algorithm in [
            Algorithm::BinarySwap,
            Algorithm::RadixK,
            Algorithm::DirectSend,
            Algorithm::Gather,
        ] {
            let c = CompositeChoice {
                algorithm,
                k: Vec::new(),
                interlace: false,
                format: WireFormat::F32,
                lz4: false,
            };
            let plan = strata_common::composite::build_plan(3, 1200, algorithm, None).unwrap();
            let honest: Vec<Span> = slots
                .iter()
                .map(|&r| plan.result[order.iter().position(|&o| o == r).unwrap()])
                .collect();
            final_spans_match_the_plan(1200, &c, &order, &slots, &honest).unwrap();
            for liar in 0..3 {
                if honest[liar].is_empty() {
                    continue; // nothing to leave out
                }
                let mut spans = honest.clone();
                spans[liar] = Span::new(0, 0);
                let (rank, e) =
                    final_spans_match_the_plan(1200, &c, &order, &slots, &spans).unwrap_err();
                assert_eq!(rank, slots[liar], "{algorithm:?}");
                assert!(e.to_string().contains("not its part"), "{e}");
            }
        }
    }

    fn cov(present: &[bool]) -> Vec<Option<Transmittance>> {
        let grid = BlockGrid::new(4, 4, 2);
        present
            .iter()
            .map(|&p| {
                p.then(|| Transmittance {
                    grid,
                    rect: Default::default(),
                    q: Vec::new(),
                })
            })
            .collect()
    }

    /// A timed-out occlusion phase blames the workers whose coverage is missing, and never
    /// the last of the order, which sends none.
    #[test]
    fn a_timed_out_occlusion_phase_blames_the_missing_coverage_but_not_the_last_worker() {
        let slots = [0, 1, 2];
        let order = [2, 0, 1];
        // Rank 0 (second) has not reported; rank 1, last, never does.
        let c = cov(&[false, false, true]);
        assert_eq!(late_ranks(&slots, &order, Some(&c), vec![0, 1, 2]), vec![0]);
        // Everyone who reports has: the workers without a result are late.
        let c = cov(&[true, false, true]);
        assert_eq!(late_ranks(&slots, &order, Some(&c), vec![1]), vec![1]);
        // After the maps: the workers without a result.
        assert_eq!(late_ranks(&slots, &order, None, vec![2]), vec![2]);
    }
}
