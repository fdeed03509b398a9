//! The scene description: which stores to draw, how, and from where.
//!
//! Scenes are TOML. Parse errors name the file, line and column (the `toml` crate's spans).
//! Store paths are relative to the scene file's folder. This is the part of the scene model
//! that the data layer needs; the renderer adds camera and transfer-function detail.

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// A whole scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Volumes (seismic cubes, CT, ...).
    #[serde(default, rename = "volume")]
    pub volumes: Vec<VolumeLayer>,
    /// Horizons.
    #[serde(default, rename = "horizon")]
    pub horizons: Vec<HorizonLayer>,
    /// Camera; the renderer frames the scene if absent.
    #[serde(default)]
    pub camera: Option<Camera>,
    /// Render settings.
    #[serde(default)]
    pub render: RenderSettings,
    /// A built-in synthetic survey to generate (once) before rendering; the layers above
    /// name its stores.
    #[serde(default)]
    pub synthetic: Option<SyntheticSpec>,
    /// How partial images are composited.
    #[serde(default)]
    pub composite: CompositeSettings,
    /// Workers: how many, where they come from, timeouts.
    #[serde(default)]
    pub cluster: ClusterSettings,
    /// A powerwall: the frame is a grid of display tiles (`render.width`/`height` are then
    /// not used).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub wall: Option<WallSettings>,
}

/// `[wall]`: a powerwall of `tiles` display tiles, each `tile_size` pixels, separated by
/// `mullion` pixels of bezel, seen as one frustum ([`crate::wall`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WallSettings {
    /// `[columns, rows]` of tiles.
    pub tiles: [u32; 2],
    /// `[width, height]` of one tile in pixels (default 1920×1080).
    #[serde(default = "default_tile_size")]
    pub tile_size: [u32; 2],
    /// `[mx, my]`: bezel widths in pixels between horizontally and vertically neighbouring
    /// tiles (default none).
    #[serde(default)]
    pub mullion: [u32; 2],
    /// The worker rank that drives each tile, row-major from the top left (default: the
    /// tiles in consecutive runs spread over the workers). A rank's tiles must be
    /// consecutive in that order.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ranks: Option<Vec<u32>>,
    /// Write the preview mosaic (the tiles with the mullions drawn in) to the output path
    /// itself, assembled from the tile files.
    #[serde(default = "yes")]
    pub preview: bool,
}

impl WallSettings {
    /// The geometry.
    pub fn geometry(&self) -> crate::wall::WallGeometry {
        crate::wall::WallGeometry {
            cols: self.tiles[0],
            rows: self.tiles[1],
            tile_w: self.tile_size[0],
            tile_h: self.tile_size[1],
            mullion_x: self.mullion[0],
            mullion_y: self.mullion[1],
        }
    }

    /// The driving rank of each tile over `workers` workers (checked).
    pub fn drivers(&self, workers: usize) -> Result<Vec<u32>, crate::wall::WallError> {
        let g = self.geometry();
        let d = match &self.ranks {
            Some(r) => r.clone(),
            None => g.default_drivers(workers),
        };
        g.check_drivers(&d, workers)?;
        Ok(d)
    }
}

fn default_tile_size() -> [u32; 2] {
    [1920, 1080]
}

/// `[composite]`: the sort-last exchange.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CompositeSettings {
    /// `direct-send`, `binary-swap`, `radix-k` (default) or `gather` (every piece to the
    /// front rank).
    #[serde(default = "default_algorithm")]
    pub algorithm: crate::composite::Algorithm,
    /// radix-k: a target k (`8`, IceT's default, chooses factors near it) or the exact
    /// factors of the worker count (`[4, 2]`).
    #[serde(default)]
    pub k: KSetting,
    /// Shuffle rows so every rank's active pixels spread over all final pieces.
    #[serde(default = "yes")]
    pub interlace: bool,
    /// Pixel precision on the wire: `f32` (exact, default) or `f16` (half the bytes).
    #[serde(default)]
    pub wire: crate::composite::WireFormat,
    /// Compress the pieces that travel over QUIC with LZ4 (byte-shuffled pixel data);
    /// shared memory never compresses. For links slower than LZ4 itself.
    #[serde(default)]
    pub lz4: bool,
}

impl Default for CompositeSettings {
    fn default() -> Self {
        CompositeSettings {
            algorithm: default_algorithm(),
            k: KSetting::default(),
            interlace: true,
            wire: Default::default(),
            lz4: false,
        }
    }
}

/// `composite.k`: one target or explicit factors.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(
    untagged,
    expecting = "a target k (e.g. 8) or exact factors (e.g. [4, 2])"
)]
pub enum KSetting {
    /// A target k.
    Target(u32),
    /// Exact factors whose product is the worker count.
    Factors(Vec<u32>),
}

impl Default for KSetting {
    fn default() -> Self {
        KSetting::Target(crate::composite::DEFAULT_TARGET_K as u32)
    }
}

impl KSetting {
    /// As a list: `[target]` or the factors.
    pub fn to_vec(&self) -> Vec<u32> {
        match self {
            KSetting::Target(k) => vec![*k],
            KSetting::Factors(f) => f.clone(),
        }
    }
}

/// `[cluster]`: the worker processes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClusterSettings {
    /// Workers to spawn (local mode) or to wait for (cluster mode), 1..=256; 0 = one per
    /// core (at least 2, at most 8).
    #[serde(default)]
    pub workers: u32,
    /// `true`: spawn the workers on this machine. `false`: wait for workers started by a
    /// launcher (`srun`, `ssh`) with `worker --connect HOST:PORT`.
    #[serde(default = "yes")]
    pub spawn: bool,
    /// UDP address the coordinator listens on (port 0: any free port).
    #[serde(default = "default_listen")]
    pub listen: String,
    /// k-d leaves per worker, 1..=64 (each worker renders one subtree of this many leaves).
    #[serde(default = "default_one_u32")]
    pub leaves_per_worker: u32,
    /// Seconds to wait for all workers to connect and set up.
    #[serde(default = "default_connect_timeout")]
    pub connect_timeout_s: f64,
    /// Seconds a frame (render + composite + gather) may take at most.
    #[serde(default = "default_frame_timeout")]
    pub frame_timeout_s: f64,
    /// Seconds of silence after which a connection counts as lost (keep-alives keep
    /// healthy connections from idling).
    #[serde(default = "default_idle_timeout")]
    pub idle_timeout_s: f64,
    /// First QUIC datagram size in bytes (1200 to 65527). 1200 is safe on any path; a
    /// cluster whose links carry jumbo frames (or one host's loopback) can start larger,
    /// which costs fewer datagrams per piece. Larger than the path allows, connections
    /// never come up.
    #[serde(default = "default_quic_mtu")]
    pub quic_mtu: u16,
    /// Rayon threads per spawned worker, at most 1024; 0 = the cores divided among the
    /// workers.
    #[serde(default)]
    pub worker_threads: u32,
    /// Local mode (`spawn = true`): bind each spawned worker process to its own block of
    /// `worker_threads` CPUs (fewer where the CPUs this process may use do not go round),
    /// cut in topology order (package, last-level cache, core), as MPI launchers bind
    /// ranks. With more workers than CPUs, each gets one CPU, shared round robin (and a
    /// warning). Each worker reports the CPUs it runs on (`cpus` in `--stats`).
    #[serde(default)]
    pub pin_workers: bool,
    /// File holding the shared secret (first line). Otherwise `$STRATA_SECRET`; local
    /// mode generates one per run when neither is set.
    #[serde(default)]
    pub secret_file: Option<PathBuf>,
    /// Where to write this run's certificate fingerprint, for launchers to pass to
    /// `worker --fingerprint-file`.
    #[serde(default)]
    pub fingerprint_file: Option<PathBuf>,
    /// Between the frames of a sequence, re-split the k-d tree from the measured per-leaf
    /// render times when the workers' imbalance (slowest / mean) exceeds
    /// `rebalance_threshold`. 0 turns re-splitting off; otherwise it must be at least 1.
    #[serde(default = "default_rebalance_threshold")]
    pub rebalance_threshold: f64,
    /// How far a re-split follows the measurement, in (0, 1] (1: all the way; smaller:
    /// damped). With `rebalance_model = "leaves"` each leaf's cost per unit of estimate is
    /// raised to this power; with `"pages"` the new cost of each box is this fraction of the
    /// measured one plus the rest of the cost in force.
    #[serde(default = "default_rebalance_damping")]
    pub rebalance_damping: f64,
    /// What a re-split distributes each leaf's measured time by: `pages` (the default: the
    /// pages its rays entered, tile by tile, so cost moves within a leaf to where the
    /// view's work is) or `leaves` (the leaf's estimated cost boxes, all scaled by one
    /// factor per leaf). `pages` needs the CPU backend's per-tile times; without any page
    /// work reported, a re-split uses `leaves`.
    #[serde(default)]
    pub rebalance_model: RebalanceModel,
    /// Which clock measures each leaf's render for a re-split (its imbalance and its
    /// costs): `cpu` (the default: the CPU time of the leaf's cast over the worker's render
    /// threads, which workers sharing cores do not inflate) or `wall` (the cast's wall
    /// time, which also counts the time its threads did not run: cores shared with other
    /// processes, waits). Where a worker reports no CPU time (the GPU backend), a re-split
    /// uses wall times.
    #[serde(default)]
    pub rebalance_clock: RebalanceClock,
    /// How image pieces travel between processes: `auto` (shared memory between processes
    /// on one host, QUIC between hosts), `quic` (QUIC everywhere) or `shm` (shared memory
    /// everywhere; an error when the processes are not all on one host).
    #[serde(default)]
    pub transport: Transport,
    /// What a worker lost during a frame (process exit, dead connection, no answer within
    /// `frame_timeout_s`, or its peers losing it) costs: `reassign` (its leaves go to the
    /// survivors and the frame is rendered again) or `fail` (the frame fails, naming it).
    #[serde(default)]
    pub on_worker_loss: OnWorkerLoss,
    /// Cluster mode (`spawn = false`): a worker that connects during a sequence (started
    /// by hand or by a launcher with the run's fingerprint and secret) replaces one that
    /// was lost, and takes load at the next frame. After a loss, the next frame waits up to
    /// this many seconds for such a replacement before rendering with the workers left
    /// (0: no wait; a replacement that comes later joins at the frame after it connects).
    #[serde(default)]
    pub replacement_wait_s: f64,
    /// Local mode (`spawn = true`): how many lost workers this run may replace with a
    /// freshly spawned worker process (0: none; the run goes on with the workers left).
    /// A replacement joins at the next frame, as one would in cluster mode; that frame
    /// waits for the replacements it spawned (while they are alive) up to
    /// `connect_timeout_s`.
    #[serde(default)]
    pub respawn: u32,
    /// Cross-worker occlusion: workers leave uncast the screen blocks that content in
    /// front of their region (owned by other workers) already makes opaque to
    /// `render.early_termination`, predicted from the previous frame of a sequence and
    /// confirmed in the current one (blocks it does not confirm are cast afterwards).
    #[serde(default = "yes")]
    pub occlusion: bool,
    /// Side in pixels of the screen blocks occlusion works in (1..=64): smaller blocks
    /// follow silhouettes and varying opacity more closely and move more bytes (two per
    /// block and worker, each way, per frame).
    #[serde(default = "default_occlusion_block")]
    pub occlusion_block: u32,
    /// When occlusion has no prediction from the previous frame (the first frame, a new
    /// order of the workers in front, a new image size), take one from a first pass at 1/4
    /// of the resolution, so single frames leave hidden rays uncast too.
    #[serde(default = "yes")]
    pub occlusion_prepass: bool,
    /// Between frames of a sequence, widen the last frame's occlusion map by how far the
    /// scene moved on screen (each block takes the most light passed within that many
    /// pixels), so a moving camera leaves fewer blocks to cast again afterwards, at the cost
    /// of casting more behind the edges of what is in front. Off by default: on the demo
    /// orbit at 8 workers it cast 7 % more samples and the frame took 6 % longer once
    /// re-casts had become cheap (docs/BENCHMARKS.md). Not applied to a `[wall]`'s frames.
    /// Without it, each worker moves the last frame's map by how far its own region moved
    /// on screen (the median point; not for a wall either); the figures above were measured
    /// against the map unmoved, before that.
    #[serde(default)]
    pub occlusion_motion: bool,
}

/// `cluster.on_worker_loss`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OnWorkerLoss {
    /// Give the lost worker's leaves to the survivors and render the frame again.
    #[default]
    Reassign,
    /// Fail the frame with an error naming the lost worker.
    Fail,
}

/// `cluster.rebalance_model`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RebalanceModel {
    /// Each leaf's measured time over its estimated cost, one factor per leaf.
    Leaves,
    /// Each leaf's measured time, divided among the pages its rays entered.
    #[default]
    Pages,
}

/// `cluster.rebalance_clock`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RebalanceClock {
    /// The leaf cast's CPU time over the worker's render threads.
    #[default]
    Cpu,
    /// The leaf cast's wall time.
    Wall,
}

/// `cluster.transport`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Transport {
    /// Shared memory between processes that share a host, QUIC otherwise.
    #[default]
    Auto,
    /// QUIC between every pair, even on one host.
    Quic,
    /// Shared memory between every pair; refused when some are on another host.
    Shm,
}

fn default_occlusion_block() -> u32 {
    2
}
fn default_rebalance_threshold() -> f64 {
    // Measured by CPU time (`rebalance_clock`), eight workers settle at a work imbalance
    // of about 1.15 with 1.1 against 1.22 with 1.25, for the same total work
    // (docs/BENCHMARKS.md, "Re-splitting by CPU time, and the defaults").
    1.1
}
fn default_rebalance_damping() -> f64 {
    0.5
}

impl ClusterSettings {
    /// Checks the ranges of the values that need no worker count or store, for an error at
    /// the key's position in the file (`--workers` and what depends on it are checked
    /// where the run starts): the key at fault and why.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        let ensure = |ok: bool, key: &'static str, why: String| {
            if ok {
                Ok(())
            } else {
                Err((key, why))
            }
        };
        ensure(
            self.workers <= 256,
            "workers",
            format!(
                "cluster.workers must lie in 0..=256 (0: one per core), got {}",
                self.workers
            ),
        )?;
        ensure(
            self.worker_threads <= 1024,
            "worker_threads",
            format!(
                "cluster.worker_threads must lie in 0..=1024 (0: the cores divided among the workers), got {}",
                self.worker_threads
            ),
        )?;
        ensure(
            (1..=64).contains(&self.leaves_per_worker),
            "leaves_per_worker",
            format!(
                "cluster.leaves_per_worker must lie in 1..=64, got {}",
                self.leaves_per_worker
            ),
        )?;
        ensure(
            self.rebalance_threshold == 0.0
                || (self.rebalance_threshold >= 1.0 && self.rebalance_threshold.is_finite()),
            "rebalance_threshold",
            format!(
                "cluster.rebalance_threshold must be 0 (off) or at least 1, got {}",
                self.rebalance_threshold
            ),
        )?;
        ensure(
            self.rebalance_damping > 0.0 && self.rebalance_damping <= 1.0,
            "rebalance_damping",
            format!(
                "cluster.rebalance_damping must lie in (0, 1], got {}",
                self.rebalance_damping
            ),
        )?;
        ensure(
            (1..=crate::occlusion::MAX_BLOCK).contains(&self.occlusion_block),
            "occlusion_block",
            format!(
                "cluster.occlusion_block must lie in 1..={}, got {}",
                crate::occlusion::MAX_BLOCK,
                self.occlusion_block
            ),
        )?;
        for (k, v) in [
            ("connect_timeout_s", self.connect_timeout_s),
            ("frame_timeout_s", self.frame_timeout_s),
            ("idle_timeout_s", self.idle_timeout_s),
        ] {
            ensure(
                v > 0.0 && v <= 1e6,
                k,
                format!("cluster.{k} must be a positive number of seconds, got {v}"),
            )?;
        }
        ensure(
            (0.0..=1e6).contains(&self.replacement_wait_s),
            "replacement_wait_s",
            format!(
                "cluster.replacement_wait_s must be 0 or a positive number of seconds, got {}",
                self.replacement_wait_s
            ),
        )?;
        ensure(
            (1200..=65527).contains(&self.quic_mtu),
            "quic_mtu",
            format!(
                "cluster.quic_mtu must lie in 1200..=65527 bytes, got {}",
                self.quic_mtu
            ),
        )?;
        ensure(
            self.listen.parse::<std::net::SocketAddr>().is_ok(),
            "listen",
            format!(
                "cluster.listen = {:?}: expected IP:PORT, e.g. 0.0.0.0:7000",
                self.listen
            ),
        )
    }
}

impl SyntheticSpec {
    /// Samples per axis of a synthetic survey: at least 8 (its earth model's layers).
    pub const MIN_AXIS: u64 = 8;
    /// Fewer than this many per axis (2^20).
    pub const MAX_AXIS: u64 = 1 << 20;
    /// At most this many traces (its horizons' grids, three f32 per trace: 3 GiB).
    pub const MAX_TRACES: u64 = 1 << 28;
    /// At most this many samples (64 GiB of f32 written to the cache folder).
    pub const MAX_SAMPLES: u64 = 1 << 34;

    /// Checks `size` against the bounds above: the offending key and why.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        Self::check_size(self.size).map_err(|why| ("size", format!("synthetic.size {why}")))
    }

    /// Whether a survey of `d` samples per axis may be generated (the bounds above; the
    /// generator holds its argument to them too): why not.
    pub fn check_size(d: [u64; 3]) -> Result<(), String> {
        let traces = d[0].saturating_mul(d[1]);
        let samples = traces.saturating_mul(d[2]);
        if d.iter()
            .any(|&n| !(Self::MIN_AXIS..Self::MAX_AXIS).contains(&n))
            || traces > Self::MAX_TRACES
            || samples > Self::MAX_SAMPLES
        {
            return Err(format!(
                "{d:?}: each axis needs at least {} samples, and fewer than 2^20 samples per trace, per inline and per crossline; at most 2^28 traces and 2^34 samples (64 GiB)",
                Self::MIN_AXIS
            ));
        }
        Ok(())
    }
}

impl Default for ClusterSettings {
    fn default() -> Self {
        ClusterSettings {
            workers: 0,
            spawn: true,
            listen: default_listen(),
            leaves_per_worker: 1,
            connect_timeout_s: default_connect_timeout(),
            frame_timeout_s: default_frame_timeout(),
            idle_timeout_s: default_idle_timeout(),
            quic_mtu: default_quic_mtu(),
            worker_threads: 0,
            pin_workers: false,
            secret_file: None,
            fingerprint_file: None,
            rebalance_threshold: default_rebalance_threshold(),
            rebalance_damping: default_rebalance_damping(),
            rebalance_model: RebalanceModel::Pages,
            rebalance_clock: RebalanceClock::Cpu,
            transport: Transport::Auto,
            on_worker_loss: OnWorkerLoss::Reassign,
            replacement_wait_s: 0.0,
            respawn: 0,
            occlusion: true,
            occlusion_block: default_occlusion_block(),
            occlusion_prepass: true,
            occlusion_motion: false,
        }
    }
}

fn default_algorithm() -> crate::composite::Algorithm {
    crate::composite::Algorithm::RadixK
}
fn default_listen() -> String {
    "127.0.0.1:0".into()
}
fn default_one_u32() -> u32 {
    1
}
fn default_connect_timeout() -> f64 {
    60.0
}
fn default_frame_timeout() -> f64 {
    600.0
}
fn default_idle_timeout() -> f64 {
    10.0
}
fn default_quic_mtu() -> u16 {
    1200
}

/// A synthetic survey that the first command needing it generates into a cache folder.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SyntheticSpec {
    /// Cache folder, relative to the scene file (holds `seismic.strata`, `horizon1..3.strata`).
    pub dir: PathBuf,
    /// Samples per axis (inline, crossline, time).
    pub size: [u64; 3],
    /// Random seed of the earth model.
    #[serde(default = "default_seed")]
    pub seed: u64,
}

/// A volume to draw.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VolumeLayer {
    /// Page-store file.
    pub store: PathBuf,
    /// Colour map name (e.g. "seismic", "grey").
    #[serde(default = "default_colormap")]
    pub colormap: String,
    /// Value window mapped onto the colour map. If absent: under a diverging map ("seismic",
    /// "bwr" or one of them reversed) over signed data, ±the 99.5th percentile of |value|;
    /// otherwise the store's range (see the worker's `dataset` module).
    #[serde(default)]
    pub window: Option<[f64; 2]>,
    /// Opacity scale (multiplies the opacity curve): finite and >= 0, above 1 allowed.
    #[serde(default = "one")]
    pub opacity: f64,
    /// Opacity curve: `[position, alpha]` points, position 0..1 across the window, linear
    /// in between. Default: a V (|amplitude|) for "seismic" and "seismic_r", opaque for
    /// "bwr" and "bwr_r", a ramp from 0.1 otherwise.
    #[serde(default)]
    pub opacity_points: Option<Vec<[f64; 2]>>,
    /// Inline, crossline and time slices through the volume, drawn opaque (by default) in
    /// the volume's colour map over its window, as seismic interpretation tools show a
    /// cube. `slices = [{ axis = "inline", index = 300 }, { axis = "time", index = 150 }]`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub slices: Vec<SliceLayer>,
}

/// A plane of a volume's grid at a fixed index along one axis.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SliceLayer {
    /// Which grid axis the slice is normal to.
    pub axis: SliceAxis,
    /// Position along that axis, in level-0 samples from the first (fractions allowed).
    pub index: f64,
    /// Opacity in [0, 1].
    #[serde(default = "one")]
    pub opacity: f64,
}

/// `axis` of a slice: the store's grid axes, as seismic cubes name them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SliceAxis {
    /// First grid axis (constant inline number).
    Inline,
    /// Second grid axis (constant crossline number).
    Crossline,
    /// Third grid axis (constant time or depth sample).
    Time,
}

impl SliceAxis {
    /// The grid axis (0, 1, 2).
    pub fn index(self) -> usize {
        match self {
            SliceAxis::Inline => 0,
            SliceAxis::Crossline => 1,
            SliceAxis::Time => 2,
        }
    }
}

/// A horizon to draw.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HorizonLayer {
    /// Page-store file.
    pub store: PathBuf,
    /// RGB colour in 0..1.
    #[serde(default = "default_color")]
    pub color: [f64; 3],
    /// Opacity in 0..1.
    #[serde(default = "one")]
    pub opacity: f64,
    /// "constant" (the colour above), "depth" (the colour map over the horizon's range) or
    /// "volume" (the value of the volume `volume` where the surface lies, in that volume's
    /// colours; where it holds no data the constant colour shows).
    #[serde(default = "default_color_by")]
    pub color_by: String,
    /// With `color_by = "volume"`: which `[[volume]]` (0-based) colours the surface.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub volume: usize,
    /// Colour map for `color_by = "depth"` (it must name a built-in map whatever `color_by`
    /// says).
    #[serde(default = "default_depth_map")]
    pub colormap: String,
}

/// What `color_by` of a horizon may say.
const COLOR_BY: &[&str] = &["constant", "depth", "volume"];

impl VolumeLayer {
    /// Checks the values no render can use, which need no store to judge (the worker checks
    /// the rest, e.g. slices against the grid, when it opens the store); the error names the
    /// key in the `[[volume]]` table and says what was expected. [`Scene::parse`] points it
    /// at its line; [`SliceLayer::check`] covers each slice.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        crate::tf::ColorMap::named(&self.colormap)
            .map_err(|e| ("colormap", format!("colormap: {e}")))?;
        if let Some(w) = self.window {
            crate::tf::check_window(w).map_err(|e| ("window", e.to_string()))?;
        }
        // A scale of the opacity curve, not an opacity: above 1 is allowed.
        if !(self.opacity >= 0.0 && self.opacity.is_finite()) {
            return Err((
                "opacity",
                format!(
                    "opacity {} must be a finite number >= 0 (it scales the opacity curve)",
                    self.opacity
                ),
            ));
        }
        if let Some(p) = &self.opacity_points {
            crate::tf::check_opacity_points(p).map_err(|e| ("opacity_points", e.to_string()))?;
            // Positions are fractions of the window: one written in data units (an
            // amplitude of -8000) left the whole window on a sliver of the curve, and the
            // volume silently invisible.
            if let Some(q) = p.iter().find(|q| !(0.0..=1.0).contains(&q[0])) {
                return Err((
                    "opacity_points",
                    format!(
                        "opacity_points positions are fractions of the window, 0 to 1, got {} (a value in data units belongs in `window`)",
                        q[0]
                    ),
                ));
            }
        }
        if self.slices.len() > crate::gpu::MAX_SLICES {
            return Err((
                "slices",
                format!(
                    "{} slices, but at most {} per volume are drawn",
                    self.slices.len(),
                    crate::gpu::MAX_SLICES
                ),
            ));
        }
        Ok(())
    }
}

impl SliceLayer {
    /// Checks what a slice's own values allow (whether its index lies inside the grid needs
    /// the store: the worker checks that); the error names the key in the slice's table.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        if !(self.index >= 0.0 && self.index.is_finite()) {
            return Err((
                "index",
                format!(
                    "index {} must be a finite number >= 0 (level-0 samples from the first)",
                    self.index
                ),
            ));
        }
        if !(0.0..=1.0).contains(&self.opacity) {
            return Err((
                "opacity",
                format!("opacity {} must lie in 0..=1", self.opacity),
            ));
        }
        Ok(())
    }
}

impl HorizonLayer {
    /// Checks the values no render can use in a scene of `volumes` volumes; the error names
    /// the key in the `[[horizon]]` table and says what was expected. The colour map must
    /// exist whatever `color_by` says, so a misspelt name fails here and not when
    /// `color_by` later changes to "depth".
    pub fn check(&self, volumes: usize) -> Result<(), (&'static str, String)> {
        if !self.color.iter().all(|c| (0.0..=1.0).contains(c)) {
            return Err(("color", format!("color {:?} must lie in 0..=1", self.color)));
        }
        if !(0.0..=1.0).contains(&self.opacity) {
            return Err((
                "opacity",
                format!("opacity {} must lie in 0..=1", self.opacity),
            ));
        }
        if !COLOR_BY.contains(&self.color_by.as_str()) {
            return Err((
                "color_by",
                format!(
                    "color_by {:?} is unknown (expected \"constant\", \"depth\" or \"volume\")",
                    self.color_by
                ),
            ));
        }
        if self.color_by == "volume" && self.volume >= volumes {
            let has = match volumes {
                0 => "the scene has no [[volume]]".to_string(),
                n => format!("the scene has {n} [[volume]], numbered from 0"),
            };
            return Err((
                "volume",
                format!(
                    "volume {} (read by color_by = \"volume\") names no [[volume]]: {has}",
                    self.volume
                ),
            ));
        }
        crate::tf::ColorMap::named(&self.colormap)
            .map_err(|e| ("colormap", format!("colormap: {e}")))?;
        Ok(())
    }
}

/// A pinhole camera in world coordinates (f64).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    /// Eye position.
    pub eye: [f64; 3],
    /// Point looked at.
    pub target: [f64; 3],
    /// Up direction.
    #[serde(default = "default_up")]
    pub up: [f64; 3],
    /// Vertical field of view in degrees, in (0, 179), and wide enough that a pixel spans
    /// at least 2⁻²⁰ rad (`camera::MIN_PIXEL_ANGLE`: finer pixels than the casters' f32 ray
    /// directions resolve): at least 0.040° at 720 pixels high, 0.059° at 1080 (a wall's
    /// whole plane, mullions included, counts as its height).
    #[serde(default = "default_fov")]
    pub fov_deg: f64,
}

/// Render settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderSettings {
    /// Image width, 1..=[`MAX_IMAGE_SIDE`].
    #[serde(default = "default_w")]
    pub width: u32,
    /// Image height, 1..=[`MAX_IMAGE_SIDE`].
    #[serde(default = "default_h")]
    pub height: u32,
    /// Host page-cache budget in MiB.
    #[serde(default = "default_cache")]
    pub cache_mb: u64,
    /// World units per unit of z (vertical exaggeration of time or depth axes).
    #[serde(default = "one")]
    pub z_scale: f64,
    /// World z grows downward (time or depth, as in seismic surveys): the renderer flips it
    /// so that the picture is not mirrored. Set false for data whose z points up (CT, MRI).
    #[serde(default = "yes")]
    pub z_down: bool,
    /// Base sampling step in units of the finest voxel spacing of the scene's volumes.
    #[serde(default = "default_step")]
    pub step: f64,
    /// LOD tolerance in pixels: a level is fine enough when its voxel covers at most `tau`
    /// pixels. 0.5 by default (two samples per pixel, Nyquist's rate): `coordinator study
    /// accuracy` put τ = 1 off the Pareto front wherever coarse levels show (the demo
    /// survey with its volume visible: 6× the RMSE of τ 0.5 for 0.8× its time).
    #[serde(default = "half")]
    pub tau: f64,
    /// Coarser levels step further (powers of two of the base step, opacity-corrected).
    #[serde(default = "yes")]
    pub adaptive_step: bool,
    /// Early ray termination at this accumulated opacity (1.0 disables it).
    #[serde(default = "default_ert")]
    pub early_termination: f64,
    /// Skip bricks whose value range maps to zero opacity.
    #[serde(default = "yes")]
    pub empty_space_skipping: bool,
    /// With empty-space skipping, the CPU caster also skips 16³-sample macrocells inside a
    /// brick whose value range maps to zero opacity (ranges computed as a page enters the
    /// atlas). The image is the same either way (under `preintegrated`, where a cell is
    /// crossed rather than skipped, within 1e-6).
    #[serde(default = "yes")]
    pub macrocells: bool,
    /// The CPU caster's atlas keeps volume samples in the data's own type (`u8`, `i8`, `u16`,
    /// `i16`) when every volume shares one and none has a no-data value, instead of `f32`:
    /// a quarter of the memory for 8-bit data, and the same image.
    #[serde(default = "yes")]
    pub compact_slots: bool,
    /// The CPU caster marches rays in SIMD packets where the CPU has AVX2 (or AVX-512) and
    /// the frame has one volume, visible under its transfer function, no gradient shading,
    /// no `preintegrated`, no `f64_accumulation`, and an atlas small enough for 32-bit
    /// gather indices; otherwise, or with false, the scalar march runs. The image is the
    /// same.
    #[serde(default = "yes")]
    pub simd: bool,
    /// Lanes per SIMD packet: 0 (default) for the widest the CPU runs (16 with AVX-512, 8
    /// with AVX2), 8 or 16 to ask for one (16 runs as 8 without AVX-512). The image is the
    /// same.
    #[serde(default)]
    pub simd_lanes: u32,
    /// After a feedback round that loaded pages, the CPU caster casts again only the tiles
    /// (16² pixels) whose rays asked for a page that was missing; the others keep their
    /// pixels, which had every page they wanted. The image is the same; false casts every
    /// tile each round.
    #[serde(default = "yes")]
    pub selective_rounds: bool,
    /// The CPU caster asks for the pages a tile lacked as soon as the tile is cast, so that
    /// they load while the rest of the frame is cast (into free cache space only). The image
    /// is the same.
    #[serde(default = "yes")]
    pub early_loads: bool,
    /// Gradient (Blinn-Phong headlight) shading of volumes.
    #[serde(default)]
    pub volume_shading: bool,
    /// Lambert headlight shading of horizons.
    #[serde(default = "yes")]
    pub lighting: bool,
    /// Atlas budget for volume bricks in MiB.
    #[serde(default = "default_atlas")]
    pub atlas_mb: u64,
    /// Atlas budget for horizon tiles in MiB.
    #[serde(default = "default_hatlas")]
    pub horizon_atlas_mb: u64,
    /// Pages uploaded into the atlas per frame at most.
    #[serde(default = "default_upload")]
    pub upload_pages_per_frame: u32,
    /// Batch rendering: frame -> feedback -> load rounds at most.
    #[serde(default = "default_rounds")]
    pub max_rounds: u32,
    /// Frame sequences: rounds each frame after an engine's first may take (0: every frame
    /// converges, up to `max_rounds`). The pages the last round asked for are loaded before
    /// the next frame, so each frame starts from the previous one's feedback.
    #[serde(default)]
    pub rounds_per_frame: u32,
    /// Page-loader threads, 1..=256.
    #[serde(default = "default_loaders")]
    pub loader_threads: u32,
    /// Background colour (linear RGB) under the image when it is flattened to PNG.
    #[serde(default)]
    pub background: [f64; 3],
    /// Which ray caster renders: `auto` (a hardware GPU if there is one and the scene fits
    /// the GPU caster, else the CPU), `cpu`, or `gpu` (any adapter, software Vulkan too).
    #[serde(default)]
    pub backend: Backend,
    /// The GPU to use: an adapter index or a case-insensitive substring of its name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gpu_adapter: Option<AdapterSelector>,
    /// How the GPU caster interpolates volume samples: `exact` (trilinear in the shader, the
    /// CPU's formula) or `hardware` (the texture unit's trilinear filter; many GPUs use 8-bit
    /// filter weights).
    #[serde(default)]
    pub gpu_filter: GpuFilter,
    /// Pre-integrated classification (seed 001): each sample composites the segment from
    /// the previous sample to it, integrated over the transfer function with the value
    /// running linearly between the two, instead of the transfer function at the sample
    /// alone. Keeps thin opacity features a coarse step would step over. Both casters;
    /// where volumes overlap the mix stays post-classified.
    #[serde(default)]
    pub preintegrated: bool,
    /// Accumulate each ray's colour in f64 instead of f32 (CPU caster only, scalar march
    /// on the general code path: slower). The accuracy study's reference uses it, so that
    /// the rounding of its many blend steps stays far below the errors it measures.
    #[serde(default)]
    pub f64_accumulation: bool,
    /// Which copy of the casters' code renders: `specialised` (compiled for the frame's
    /// effects only, so an unused effect costs nothing) or `general` (one path with every
    /// effect compiled in, deciding at run time). The image is the same; stats and the log
    /// name the effects and the path of every frame.
    #[serde(default)]
    pub variant: CodePath,
}

/// `render.variant`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CodePath {
    /// The code compiled for the frame's effect set.
    #[default]
    #[serde(alias = "specialized")]
    Specialised,
    /// The code with every effect compiled in.
    General,
}

/// `render.gpu_filter`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GpuFilter {
    /// Trilinear interpolation in the shader, operation for operation the CPU's.
    #[default]
    Exact,
    /// The texture unit's trilinear filter over a 3D-texture pool.
    Hardware,
}

/// `render.backend`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// A hardware GPU when there is one and the scene fits the GPU caster, else the CPU.
    #[default]
    Auto,
    /// The CPU caster (rayon).
    Cpu,
    /// The wgpu caster on any adapter, Mesa's software Vulkan (lavapipe) included.
    Gpu,
}

/// `render.gpu_adapter`: an index into the adapter list or a substring of its name.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(
    untagged,
    expecting = "an adapter index (e.g. 0) or part of its name (e.g. \"nvidia\")"
)]
pub enum AdapterSelector {
    /// The adapter's index in wgpu's list.
    Index(u32),
    /// A case-insensitive substring of the adapter's name.
    Name(String),
}

impl std::fmt::Display for AdapterSelector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            AdapterSelector::Index(i) => write!(f, "{i}"),
            AdapterSelector::Name(n) => f.write_str(n),
        }
    }
}

/// The largest image side in pixels (`render.width`, `render.height`, `--size`).
pub const MAX_IMAGE_SIDE: u32 = 32768;

impl RenderSettings {
    /// Checks the values no render can use; the error names the key (under `[render]`)
    /// and says what was expected. [`Scene::parse`] points it at its line.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        // Every entry point (render, study, benches) allocates frames of this size.
        for (key, v) in [("width", self.width), ("height", self.height)] {
            if !(1..=MAX_IMAGE_SIDE).contains(&v) {
                return Err((
                    key,
                    format!("render.{key} must lie in 1..={MAX_IMAGE_SIDE}, got {v}"),
                ));
            }
        }
        for (key, v) in [
            ("step", self.step),
            ("tau", self.tau),
            ("z_scale", self.z_scale),
        ] {
            if !(v > 0.0 && v.is_finite()) {
                return Err((
                    key,
                    format!("render.{key} must be a positive number, got {v}"),
                ));
            }
        }
        // The display transform scales the stores' z by it; within these bounds that keeps
        // every accepted store transform invertible in f64.
        if !(1e-6..=1e6).contains(&self.z_scale) {
            return Err((
                "z_scale",
                format!(
                    "render.z_scale must lie in [1e-6, 1e6], got {}",
                    self.z_scale
                ),
            ));
        }
        // (0 had been accepted and quietly taken as 1.)
        for (key, v) in [
            ("max_rounds", self.max_rounds),
            ("upload_pages_per_frame", self.upload_pages_per_frame),
        ] {
            if v == 0 {
                return Err((key, format!("render.{key} must be at least 1, got 0")));
            }
        }
        if self.step < 1e-3 || self.step > 1e3 {
            return Err((
                "step",
                format!(
                    "render.step must lie in [0.001, 1000] voxels, got {}",
                    self.step
                ),
            ));
        }
        if !(self.early_termination > 0.0 && self.early_termination <= 1.0) {
            return Err((
                "early_termination",
                format!(
                    "render.early_termination must lie in (0, 1], got {}",
                    self.early_termination
                ),
            ));
        }
        if self.cache_mb == 0 {
            return Err(("cache_mb", "render.cache_mb must be at least 1".into()));
        }
        if !self.background.iter().all(|c| (0.0..=1.0).contains(c)) {
            return Err((
                "background",
                format!(
                    "render.background {:?} must lie in 0..=1 (linear RGB)",
                    self.background
                ),
            ));
        }
        for (key, v) in [
            ("atlas_mb", self.atlas_mb),
            ("horizon_atlas_mb", self.horizon_atlas_mb),
        ] {
            if v == 0 {
                return Err((key, format!("render.{key} must be at least 1")));
            }
        }
        if ![0, 8, 16].contains(&self.simd_lanes) {
            return Err((
                "simd_lanes",
                format!(
                    "render.simd_lanes must be 0 (the widest the CPU runs), 8 or 16, got {}",
                    self.simd_lanes
                ),
            ));
        }
        if self.loader_threads == 0 || self.loader_threads > 256 {
            return Err((
                "loader_threads",
                format!(
                    "render.loader_threads must lie in 1..=256, got {}",
                    self.loader_threads
                ),
            ));
        }
        Ok(())
    }
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            width: default_w(),
            height: default_h(),
            cache_mb: default_cache(),
            z_scale: 1.0,
            z_down: true,
            step: default_step(),
            tau: 0.5,
            adaptive_step: true,
            early_termination: default_ert(),
            empty_space_skipping: true,
            macrocells: true,
            compact_slots: true,
            simd: true,
            simd_lanes: 0,
            selective_rounds: true,
            early_loads: true,
            volume_shading: false,
            lighting: true,
            atlas_mb: default_atlas(),
            horizon_atlas_mb: default_hatlas(),
            upload_pages_per_frame: default_upload(),
            max_rounds: default_rounds(),
            rounds_per_frame: 0,
            loader_threads: default_loaders(),
            background: [0.0; 3],
            backend: Backend::Auto,
            gpu_adapter: None,
            gpu_filter: GpuFilter::Exact,
            preintegrated: false,
            f64_accumulation: false,
            variant: CodePath::Specialised,
        }
    }
}

fn default_colormap() -> String {
    "seismic".into()
}
fn default_color() -> [f64; 3] {
    [0.9, 0.8, 0.3]
}
fn default_up() -> [f64; 3] {
    [0.0, 0.0, -1.0]
}
fn default_fov() -> f64 {
    35.0
}
fn default_w() -> u32 {
    1280
}
fn default_h() -> u32 {
    720
}
fn default_cache() -> u64 {
    1024
}
fn half() -> f64 {
    0.5
}

fn one() -> f64 {
    1.0
}
fn yes() -> bool {
    true
}
fn default_seed() -> u64 {
    1
}
fn is_zero(v: &usize) -> bool {
    *v == 0
}
fn default_color_by() -> String {
    "constant".into()
}
fn default_depth_map() -> String {
    "viridis".into()
}
fn default_step() -> f64 {
    1.0
}
fn default_ert() -> f64 {
    0.99
}
fn default_atlas() -> u64 {
    512
}
fn default_hatlas() -> u64 {
    64
}
fn default_upload() -> u32 {
    512
}
fn default_rounds() -> u32 {
    24
}
fn default_loaders() -> u32 {
    2
}

/// 1-based line and column of byte `offset` in `text` (an offset inside a multi-byte
/// character counts as that character).
pub fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let mut end = offset.min(text.len());
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    let before = &text[..end];
    let line = before.matches('\n').count() + 1;
    // Characters, not bytes: a non-ASCII name earlier on the line must not shift it.
    let col = before[before.rfind('\n').map_or(0, |i| i + 1)..]
        .chars()
        .count()
        + 1;
    (line, col)
}

/// A scene that failed to parse: the message names file, line and column.
#[derive(Debug, thiserror::Error)]
#[error("{path}:{line}:{column}: {message}")]
pub struct SceneError {
    /// The scene file.
    pub path: PathBuf,
    /// 1-based line.
    pub line: usize,
    /// 1-based column.
    pub column: usize,
    /// What was wrong.
    pub message: String,
}

/// Runs the layers' own checks ([`VolumeLayer::check`], [`SliceLayer::check`],
/// [`HorizonLayer::check`]) and points an error at the key in its `[[volume]]` or
/// `[[horizon]]` table, so that a bad value does not wait for the workers to open the
/// stores (whose errors have no position).
fn check_layers(path: &Path, text: &str, scene: &Scene) -> Result<(), SceneError> {
    let error = |(line, column), message| SceneError {
        path: path.to_path_buf(),
        line,
        column,
        message,
    };
    for (i, v) in scene.volumes.iter().enumerate() {
        v.check().map_err(|(key, what)| {
            error(
                key_position_in(text, "[[volume]]", i, key),
                format!("volume {i}: {what}"),
            )
        })?;
        for (j, s) in v.slices.iter().enumerate() {
            s.check().map_err(|(key, what)| {
                let at = slice_key_position(text, i, j, key)
                    .unwrap_or_else(|| key_position_in(text, "[[volume]]", i, "slices"));
                error(at, format!("volume {i}: slice {j}: {what}"))
            })?;
        }
    }
    for (i, h) in scene.horizons.iter().enumerate() {
        h.check(scene.volumes.len()).map_err(|(key, what)| {
            // `volume` defaults to 0: when it is not written, the `color_by` that reads it
            // is what to change.
            let key = match key {
                "volume" if find_key_in(text, "[[horizon]]", i, key).is_none() => "color_by",
                k => k,
            };
            error(
                key_position_in(text, "[[horizon]]", i, key),
                format!("horizon {i}: {what}"),
            )
        })?;
    }
    Ok(())
}

/// Line and column of `key` in slice `j` of volume `i`. Slices are inline tables (or
/// `[[volume.slices]]` tables), which the line scan of [`key_position_in`] does not look
/// into: the value's span in the parsed TOML finds the slice, and the key is the name
/// before its `=` (the value itself when the key is written otherwise, e.g. quoted).
/// `None` when the slice or the key is not in `text`.
fn slice_key_position(text: &str, i: usize, j: usize, key: &str) -> Option<(usize, usize)> {
    #[derive(Deserialize)]
    struct Volumes {
        #[serde(default)]
        volume: Vec<Slices>,
    }
    #[derive(Deserialize)]
    struct Slices {
        #[serde(default)]
        slices: Vec<std::collections::BTreeMap<String, toml::Spanned<toml::Value>>>,
    }
    let spans: Volumes = toml::from_str(text).ok()?;
    let value = spans.volume.get(i)?.slices.get(j)?.get(key)?.span().start;
    let before = text.get(..value)?.trim_end().strip_suffix('=')?.trim_end();
    let at = before.strip_suffix(key).map_or(value, str::len);
    Some(line_col(text, at))
}

impl Scene {
    /// Parses scene text; `path` names the file in errors and anchors relative store paths.
    pub fn parse(path: &Path, text: &str) -> Result<Scene, SceneError> {
        let mut scene: Scene = toml::from_str(text).map_err(|e| {
            let (line, column) = e.span().map_or((1, 1), |s| line_col(text, s.start));
            SceneError {
                path: path.to_path_buf(),
                line,
                column,
                message: e.message().to_string(),
            }
        })?;
        // A camera without `up` takes the world's up as the display shows it (−z when z
        // grows downward, +z otherwise), as the camera made for a scene without one does.
        if let Some(c) = &mut scene.camera {
            let given = text
                .parse::<toml::Table>()
                .ok()
                .and_then(|t| t.get("camera")?.get("up").map(|_| ()))
                .is_some();
            if !given {
                c.up = crate::camera::world_up(&scene.render);
            }
        }
        let base = path.parent().unwrap_or(Path::new("."));
        for v in &mut scene.volumes {
            if v.store.is_relative() {
                v.store = base.join(&v.store);
            }
        }
        for h in &mut scene.horizons {
            if h.store.is_relative() {
                h.store = base.join(&h.store);
            }
        }
        if let Some(s) = &mut scene.synthetic {
            if s.dir.is_relative() {
                s.dir = base.join(&s.dir);
            }
        }
        for f in [
            &mut scene.cluster.secret_file,
            &mut scene.cluster.fingerprint_file,
        ]
        .into_iter()
        .flatten()
        {
            if f.is_relative() {
                *f = base.join(&*f);
            }
        }
        let at = |section: &str, key: &str, message: String| {
            let (line, column) = key_position(text, section, key);
            SceneError {
                path: path.to_path_buf(),
                line,
                column,
                message,
            }
        };
        scene
            .render
            .check()
            .map_err(|(key, message)| at("render", key, message))?;
        scene
            .cluster
            .check()
            .map_err(|(key, message)| at("cluster", key, message))?;
        if let KSetting::Factors(f) = &scene.composite.k {
            if f.len() < 2 || f.iter().any(|&k| k < 2) {
                return Err(at(
                    "composite",
                    "k",
                    format!(
                        "composite.k = {f:?}: exact factors are a list of at least two, each at least 2 (a target k is a number, e.g. k = 8)"
                    ),
                ));
            }
        }
        if let Some(sy) = &scene.synthetic {
            sy.check()
                .map_err(|(key, message)| at("synthetic", key, message))?;
        }
        check_layers(path, text, &scene)?;
        if let Some(c) = &scene.camera {
            use crate::camera::{View, ViewError};
            let (w, h) = (scene.render.width.max(1), scene.render.height.max(1));
            // A wall's view is its whole plane's (what its frames use); a wall layout out of
            // range is reported below, at its own key.
            let view = match &scene.wall {
                Some(wall) if wall.geometry().check().is_ok() => {
                    View::wall(c, &scene.render, &wall.geometry())
                }
                _ => View::new(c, &scene.render, w, h),
            };
            view.map_err(|e| {
                let (section, key) = match &e {
                    ViewError::Fov(_) | ViewError::TooNarrow { .. } => ("camera", "fov_deg"),
                    ViewError::NotFinite(key) => ("camera", *key),
                    ViewError::EyeIsTarget => ("camera", "target"),
                    ViewError::UpParallel => ("camera", "up"),
                    ViewError::ZScale(_) => ("render", "z_scale"),
                    ViewError::Size(..) | ViewError::Wall(_) => ("render", "width"),
                };
                at(section, key, e.to_string())
            })?;
        }
        if let Some(w) = &scene.wall {
            w.geometry().check().map_err(|message| {
                // Point at the key of the `[wall]` section the message names.
                let key = ["tiles", "tile_size", "mullion"]
                    .into_iter()
                    .find(|k| message.starts_with(&format!("wall.{k} ")))
                    .unwrap_or("tiles");
                let (line, column) = key_position(text, "wall", key);
                SceneError {
                    path: path.to_path_buf(),
                    line,
                    column,
                    message,
                }
            })?;
            if let Some(r) = &w.ranks {
                let tiles = w.geometry().tiles() as usize;
                if r.len() != tiles {
                    let (line, column) = key_position(text, "wall", "ranks");
                    return Err(SceneError {
                        path: path.to_path_buf(),
                        line,
                        column,
                        message: format!(
                            "wall.ranks names {} ranks for {tiles} tiles (one per tile, row-major from the top left)",
                            r.len()
                        ),
                    });
                }
            }
        }
        Ok(scene)
    }

    /// Serializes the scene as TOML.
    pub fn to_toml(&self) -> Result<String, String> {
        // Paths are written as TOML strings: one that is not UTF-8 (a folder name in
        // another encoding) cannot be.
        toml::to_string(self).map_err(|e| {
            format!("the scene cannot be written as TOML for the workers ({e}); a path in it is probably not UTF-8")
        })
    }
}

/// Line and column of `key` inside the scene's `[section]` (the section's header when the
/// key is not written there, 1, 1 without the section, e.g. for a value that came from
/// `--set`).
fn key_position(text: &str, section: &str, key: &str) -> (usize, usize) {
    key_position_in(text, &format!("[{section}]"), 0, key)
}

/// Line and column of `key` in the `nth` table headed `header` (`[render]`, or
/// `[[horizon]]` for an array of tables): the header's when the key is not written there,
/// 1, 1 without the table.
fn key_position_in(text: &str, header: &str, nth: usize, key: &str) -> (usize, usize) {
    find_key_in(text, header, nth, key)
        .or_else(|| find_table(text, header, nth))
        .map_or((1, 1), |at| line_col(text, at))
}

/// Byte offset of `key` written in the `nth` table headed `header`, if it is.
fn find_key_in(text: &str, header: &str, nth: usize, key: &str) -> Option<usize> {
    scan_table(text, header, nth, Some(key)).0
}

/// Byte offset of the `nth` header `header`, if there is one.
fn find_table(text: &str, header: &str, nth: usize) -> Option<usize> {
    scan_table(text, header, nth, None).1
}

/// Scans `text` line by line for the `nth` table headed `header` and, inside it, a line
/// that sets `key`: the offsets of that line (`None` if not found) and of the header.
/// The table a header line opens (`[render]`, `[[ volume ]]`, `[a . b]  # note`), as
/// `(array of tables, dotted name without spaces)`; `None` for any other line, such as a
/// row of a multi-line array (`[0.0, 1.0],`), which does not end the table it is in.
fn header_of(line: &str) -> Option<(bool, String)> {
    let t = line.split('#').next().unwrap_or("").trim();
    let (array, inner) = if let Some(r) = t.strip_prefix("[[").and_then(|r| r.strip_suffix("]]")) {
        (true, r)
    } else {
        (false, t.strip_prefix('[')?.strip_suffix(']')?)
    };
    let inner = inner.trim();
    let first = inner.chars().next()?;
    if !(first.is_ascii_alphabetic() || first == '_' || first == '"' || first == '\'')
        || inner.contains([',', '[', ']', '='])
    {
        return None;
    }
    let name: Vec<&str> = inner.split('.').map(str::trim).collect();
    Some((array, name.join(".")))
}

fn scan_table(
    text: &str,
    header: &str,
    nth: usize,
    key: Option<&str>,
) -> (Option<usize>, Option<usize>) {
    let want = header_of(header);
    let mut offset = 0;
    let mut seen = 0;
    let mut inside: Option<usize> = None;
    for line in text.split_inclusive('\n') {
        let t = line.trim_start();
        let at = offset + (line.len() - t.len());
        offset += line.len();
        if let Some(this) = header_of(t) {
            if inside.is_some() {
                break;
            }
            if Some(&this) == want.as_ref() {
                if seen == nth {
                    inside = Some(at);
                    if key.is_none() {
                        break;
                    }
                }
                seen += 1;
            }
        } else if let (Some(_), Some(key)) = (inside, key) {
            if t.starts_with(key) && t[key.len()..].trim_start().starts_with('=') {
                return (Some(at), inside);
            }
        }
    }
    (None, inside)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wall_section_parses_and_bad_values_point_at_their_key() {
        let s = Scene::parse(
            Path::new("w.toml"),
            "[wall]\ntiles = [3, 2]\nmullion = [40, 60]\n",
        )
        .unwrap();
        let w = s.wall.as_ref().unwrap();
        assert_eq!(w.tiles, [3, 2]);
        assert_eq!(w.tile_size, [1920, 1080]);
        assert_eq!(w.mullion, [40, 60]);
        assert!(w.preview);
        assert_eq!(w.drivers(4).unwrap(), [0, 0, 1, 2, 2, 3]);
        let e = Scene::parse(
            Path::new("w.toml"),
            "[render]\nwidth = 8\n[wall]\ntiles = [3, 2]\ntile_size = [0, 10]\n",
        )
        .unwrap_err();
        assert_eq!((e.line, e.column), (5, 1), "{e}");
        assert!(e.to_string().contains("wall.tile_size"), "{e}");
        let e = Scene::parse(
            Path::new("w.toml"),
            "[wall]\ntiles = [2, 1]\nranks = [0, 1, 2]\n",
        )
        .unwrap_err();
        assert_eq!((e.line, e.column), (3, 1), "{e}");
        let e = Scene::parse(Path::new("w.toml"), "[wall]\ntile_size = [4, 4]\n").unwrap_err();
        assert!(e.to_string().contains("tiles"), "{e}");
        let e =
            Scene::parse(Path::new("w.toml"), "[wall]\ntiles = [2, 1]\nbezel = 3\n").unwrap_err();
        assert_eq!(e.line, 3, "{e}");
        // The field of view is checked against the wall's plane (2 × 1080 + 60 pixels high:
        // at least 0.122°), not render.height (720: 0.040°).
        let camera = "[camera]\neye = [0, 0, 0]\ntarget = [1, 0, 0]\nfov_deg = 0.1\n";
        let wall = "[wall]\ntiles = [3, 2]\nmullion = [40, 60]\n";
        Scene::parse(Path::new("w.toml"), camera).unwrap();
        let e = Scene::parse(Path::new("w.toml"), &format!("{camera}{wall}")).unwrap_err();
        assert_eq!((e.line, e.column), (4, 1), "{e}");
        assert!(e.to_string().contains("2220 pixels"), "{e}");
    }

    /// `[cluster]`, `composite.k` and `[synthetic]` are checked as the file is read, at
    /// the key's line (they had been checked only as a run started, with no position, and
    /// after a synthetic survey was generated).
    #[test]
    fn cluster_composite_and_synthetic_values_are_checked_at_their_keys() {
        let p = Path::new("c.toml");
        for (text, line, needle) in [
            (
                "[render]\nwidth = 8\n[cluster]\nspawn = true\nocclusion_block = 0\n",
                5,
                "occlusion_block",
            ),
            (
                "[cluster]\nleaves_per_worker = 65\n",
                2,
                "leaves_per_worker",
            ),
            ("[cluster]\nframe_timeout_s = -1\n", 2, "frame_timeout_s"),
            ("[cluster]\nlisten = \"localhost:7000\"\n", 2, "IP:PORT"),
            ("[cluster]\nworkers = 300\n", 2, "cluster.workers"),
            ("[cluster]\nrebalance_damping = 0\n", 2, "rebalance_damping"),
            ("[composite]\nk = [2]\n", 2, "exact factors"),
            ("[composite]\nk = [4, 1]\n", 2, "exact factors"),
            (
                "[synthetic]\ndir = \"s\"\nsize = [1000000, 1000000, 1000]\n",
                3,
                "2^34 samples",
            ),
            (
                "[synthetic]\ndir = \"s\"\nsize = [4, 64, 64]\n",
                3,
                "synthetic.size",
            ),
        ] {
            let e = Scene::parse(p, text).unwrap_err();
            assert_eq!(e.line, line, "{text}: {e}");
            assert!(e.to_string().contains(needle), "{text}: {e}");
        }
        for key in ["max_rounds", "upload_pages_per_frame"] {
            let e = Scene::parse(p, &format!("[render]\nwidth = 8\n{key} = 0\n")).unwrap_err();
            assert_eq!(e.line, 3, "{e}");
            assert!(e.to_string().contains(key), "{e}");
        }
        // The defaults and the limits themselves are accepted.
        Scene::parse(p, "[cluster]\nworkers = 256\nocclusion_block = 64\n[composite]\nk = [4, 2]\n[synthetic]\ndir = \"s\"\nsize = [8, 8, 8]\n").unwrap();
        Scene::parse(p, "[composite]\nk = 8\n").unwrap();
    }

    #[test]
    fn parses_and_resolves_paths() {
        let s = Scene::parse(
            Path::new("/data/survey/scene.toml"),
            "[[volume]]\nstore = \"cube.strata\"\n[[horizon]]\nstore = \"/abs/h.strata\"\n[render]\nwidth = 64\n",
        )
        .unwrap();
        assert_eq!(
            s.volumes[0].store,
            PathBuf::from("/data/survey/cube.strata")
        );
        assert_eq!(s.horizons[0].store, PathBuf::from("/abs/h.strata"));
        assert_eq!(s.render.width, 64);
        assert_eq!(s.render.height, 720);
    }

    #[test]
    fn a_camera_without_up_takes_the_worlds_up_as_displayed() {
        let up = |render: &str, camera_up: &str| {
            let text = format!(
                "[render]\n{render}\n[camera]\neye = [0, 0, 0]\ntarget = [1, 0, 0]\n{camera_up}"
            );
            Scene::parse(Path::new("s.toml"), &text)
                .unwrap()
                .camera
                .unwrap()
                .up
        };
        assert_eq!(up("z_down = true", ""), [0.0, 0.0, -1.0]);
        assert_eq!(up("z_down = false", ""), [0.0, 0.0, 1.0]);
        assert_eq!(up("", ""), [0.0, 0.0, -1.0], "z grows downward by default");
        assert_eq!(up("z_down = false", "up = [0, 1, 0]"), [0.0, 1.0, 0.0]);
    }

    #[test]
    fn bad_values_point_at_their_key() {
        let e = Scene::parse(
            Path::new("s.toml"),
            "[render]\nwidth = 64\n  step = 0.0\n[camera]\neye = [0, 0, 0]\ntarget = [1, 0, 0]\n",
        )
        .unwrap_err();
        assert_eq!((e.line, e.column), (3, 3), "{e}");
        assert!(e.to_string().starts_with("s.toml:3:3: render.step"), "{e}");
        for bad in ["0", "70000"] {
            let e = Scene::parse(
                Path::new("s.toml"),
                &format!(
                    "[render]\nheight = {bad}\n[camera]\neye = [0, 0, 0]\ntarget = [1, 0, 0]\n"
                ),
            )
            .unwrap_err();
            assert!(
                e.to_string()
                    .starts_with("s.toml:2:1: render.height must lie in 1..=32768"),
                "{e}"
            );
        }
        let camera = |body: &str| {
            Scene::parse(
                Path::new("c.toml"),
                &format!("[render]\nwidth = 64\n\n[camera]\neye = [0, 0, 0]\n{body}"),
            )
        };
        let e = camera("target = [1, 0, 0]\nfov_deg = 0.0\n").unwrap_err();
        assert_eq!((e.line, e.column), (7, 1), "{e}");
        assert!(e.to_string().contains("camera.fov_deg"), "{e}");
        // Pixels finer than f32 ray directions resolve (720 pixels high: at least 0.03934°,
        // suggested rounded up).
        let e = camera("target = [1, 0, 0]\nfov_deg = 0.039\n").unwrap_err();
        assert_eq!((e.line, e.column), (7, 1), "{e}");
        assert!(e.to_string().contains("at least 0.040"), "{e}");
        camera("target = [1, 0, 0]\nfov_deg = 0.040\n").unwrap();
        let e = camera("target = [0, 0, 0]\n").unwrap_err();
        assert_eq!(e.line, 6, "{e}");
        assert!(e.to_string().contains("coincide"), "{e}");
        let e = camera("target = [1, 0, 0]\nup = [0, 0, 0]\n").unwrap_err();
        assert_eq!(e.line, 7, "{e}");
        assert!(e.to_string().contains("camera.up"), "{e}");
        // Columns count characters: a non-ASCII value before the error on its line does
        // not shift it (bytes had put it five further).
        assert_eq!(line_col("a\nstore = \"ééééé\", x", 24), (2, 18));
        // Untagged settings say what they expect.
        let e = Scene::parse(Path::new("k.toml"), "[composite]\nk = \"8\"\n").unwrap_err();
        assert!(e.to_string().contains("a target k"), "{e}");
        let e = Scene::parse(Path::new("g.toml"), "[render]\ngpu_adapter = -1\n").unwrap_err();
        assert!(e.to_string().contains("an adapter index"), "{e}");
        // NaN names its own key (it had been reported as the eye on the target).
        let e = camera("target = [nan, 0.0, 0.0]\n").unwrap_err();
        assert_eq!(e.line, 6, "{e}");
        assert!(
            e.to_string().contains("camera.target must be three finite"),
            "{e}"
        );
        // A key the file does not hold (the default up along the view): its section.
        let e = Scene::parse(
            Path::new("c.toml"),
            "[camera]\neye = [0, 0, 0]\ntarget = [0, 0, 5]\n",
        )
        .unwrap_err();
        assert_eq!((e.line, e.column), (1, 1), "{e}");
        assert!(camera("target = [1, 0, 0]\n").is_ok());
        // The second horizon's colour: its own line, not the first's.
        let e = Scene::parse(
            Path::new("h.toml"),
            "[[horizon]]\nstore = \"a\"\ncolor = [1, 0, 0]\n\n[[horizon]]\nstore = \"b\"\ncolor = [0, nan, 0]\n",
        )
        .unwrap_err();
        assert_eq!((e.line, e.column), (7, 1), "{e}");
        assert!(e.to_string().contains("horizon 1: color"), "{e}");
        let e = Scene::parse(
            Path::new("b.toml"),
            "[render]  # settings\nbackground = [0, 0, inf]\n",
        )
        .unwrap_err();
        assert_eq!((e.line, e.column), (2, 1), "{e}");
    }

    /// Parses `text` as `s.toml`, which must fail.
    fn error(text: &str) -> SceneError {
        Scene::parse(Path::new("s.toml"), text).unwrap_err()
    }

    /// Two volumes, the second one's keys after `second` (indented lines keep their column).
    fn two_volumes(second: &str) -> String {
        format!("[[volume]]\nstore = \"a\"\n\n[[volume]]\nstore = \"b\"\n{second}")
    }

    /// Spaced headers (`[[ volume ]]`, valid TOML) count as the tables they open, and a
    /// multi-line array's rows (lines starting with `[`) do not end the table: errors after
    /// them point at their own key (they had pointed at another table's key, or at the
    /// header).
    #[test]
    fn positions_survive_spaced_headers_and_multi_line_arrays() {
        let e = error(
            "[[ volume ]]\nstore = \"a\"\ncolormap = \"jet\"\n[[volume]]\nstore = \"b\"\ncolormap = \"grey\"\n",
        );
        assert_eq!((e.line, e.column), (3, 1), "{e}");
        assert!(e.to_string().contains("volume 0"), "{e}");
        let e = error(
            "[[volume]]\nstore = \"a\"\nopacity_points = [\n  [0.0, 0.0],\n  [1.0, 1.0],\n]\nopacity = -1\n",
        );
        assert_eq!((e.line, e.column), (7, 1), "{e}");
        let e = error("[ render ]  # the frame\nwidth = 8\nstep = 0\n");
        assert_eq!((e.line, e.column), (3, 1), "{e}");
        assert_eq!(header_of("[[ a . b ]] # x"), Some((true, "a.b".into())));
        assert_eq!(header_of("[0.0, 1.0],"), None);
        assert_eq!(header_of("[1.0]"), None);
    }

    #[test]
    fn an_unknown_volume_colormap_points_at_its_key() {
        let e = error(&two_volumes("  colormap = \"virdis\"\n"));
        assert_eq!((e.line, e.column), (6, 3), "{e}");
        assert_eq!(
            e.to_string(),
            "s.toml:6:3: volume 1: colormap: unknown colour map \"virdis\" (expected one of \
             seismic, bwr, grey, viridis, bone, hot, or one of them reversed as NAME_r)"
        );
        let s = Scene::parse(
            Path::new("s.toml"),
            &two_volumes("colormap = \"viridis_r\"\n"),
        );
        assert_eq!(s.unwrap().volumes[1].colormap, "viridis_r");
    }

    #[test]
    fn a_negative_volume_opacity_points_at_its_key() {
        for bad in ["-0.5", "nan", "inf"] {
            let e = error(&two_volumes(&format!(
                "colormap = \"grey\"\nopacity = {bad}\n"
            )));
            assert_eq!((e.line, e.column), (7, 1), "{e}");
            assert!(
                e.to_string().starts_with(&format!(
                    "s.toml:7:1: volume 1: opacity {} must be a finite number >= 0",
                    bad.parse::<f64>().unwrap()
                )),
                "{e}"
            );
        }
        // A scale of the opacity curve: above 1 is fine.
        let s = Scene::parse(Path::new("s.toml"), &two_volumes("opacity = 4\n")).unwrap();
        assert_eq!(s.volumes[1].opacity, 4.0);
    }

    #[test]
    fn a_reversed_volume_window_points_at_its_key() {
        let e = error(&two_volumes("window = [1.0, -1.0]\n"));
        assert_eq!((e.line, e.column), (6, 1), "{e}");
        assert_eq!(
            e.to_string(),
            "s.toml:6:1: volume 1: window must be two finite values lo < hi, got [1, -1]"
        );
        let e = error(&two_volumes("window = [1e8, 1.00000001e8]\n"));
        assert_eq!((e.line, e.column), (6, 1), "{e}");
        assert!(e.message.contains("distinct finite values in f32"), "{e}");
    }

    #[test]
    fn bad_opacity_points_point_at_their_key() {
        let e = error(&two_volumes(
            "opacity = 1\nopacity_points = [[0.0, 0.0], [1.0, 1.5]]\n",
        ));
        assert_eq!((e.line, e.column), (7, 1), "{e}");
        assert_eq!(
            e.to_string(),
            "s.toml:7:1: volume 1: opacity_points alphas must lie in [0, 1], got 1.5"
        );
        let e = error(&two_volumes("opacity_points = [[0.5, 0.0], [0.2, 1.0]]\n"));
        assert!(
            e.message.contains("must not decrease (0.2 after 0.5)"),
            "{e}"
        );
        let e = error(&two_volumes(
            "opacity_points = [[-8000.0, 1.0], [0.0, 0.0], [8000.0, 1.0]]\n",
        ));
        assert!(e.message.contains("fractions of the window"), "{e}");
        assert_eq!(e.line, 6, "{e}");
        let e = error(&two_volumes("opacity_points = [[inf, 0.0]]\n"));
        assert!(
            e.message.contains("positions must be finite, got inf"),
            "{e}"
        );
        let e = error(&two_volumes("opacity_points = []\n"));
        assert!(e.message.contains("at least one"), "{e}");
    }

    #[test]
    fn a_slice_opacity_out_of_range_points_at_its_key() {
        // Inline tables, the bad one on the third line of the array.
        let e = error(&two_volumes(
            "slices = [\n  { axis = \"inline\", index = 3 },\n  { axis = \"time\", index = 2, opacity = 1.5 },\n]\n",
        ));
        assert_eq!((e.line, e.column), (8, 31), "{e}");
        assert_eq!(
            e.to_string(),
            "s.toml:8:31: volume 1: slice 1: opacity 1.5 must lie in 0..=1"
        );
        // As `[[volume.slices]]` tables.
        let e = error(&two_volumes(
            "[[volume.slices]]\naxis = \"inline\"\nindex = 3\n[[volume.slices]]\naxis = \"time\"\nindex = 2\n opacity = -0.5\n",
        ));
        assert_eq!((e.line, e.column), (12, 2), "{e}");
        assert!(
            e.message.starts_with("volume 1: slice 1: opacity -0.5"),
            "{e}"
        );
    }

    #[test]
    fn a_negative_slice_index_points_at_its_key() {
        let e = error(&two_volumes(
            "slices = [{ axis = \"crossline\", index = -3 }]\n",
        ));
        assert_eq!((e.line, e.column), (6, 33), "{e}");
        assert_eq!(
            e.to_string(),
            "s.toml:6:33: volume 1: slice 0: index -3 must be a finite number >= 0 (level-0 samples from the first)"
        );
    }

    #[test]
    fn too_many_slices_point_at_their_key() {
        let slices = vec!["{ axis = \"time\", index = 1 }"; crate::gpu::MAX_SLICES + 1].join(", ");
        let e = error(&two_volumes(&format!(
            "colormap = \"grey\"\nslices = [{slices}]\n"
        )));
        assert_eq!((e.line, e.column), (7, 1), "{e}");
        assert_eq!(
            e.to_string(),
            "s.toml:7:1: volume 1: 17 slices, but at most 16 per volume are drawn"
        );
    }

    /// A volume and two horizons, the second one's keys after `second`.
    fn two_horizons(second: &str) -> String {
        format!(
            "[[volume]]\nstore = \"v\"\n\n[[horizon]]\nstore = \"a\"\ncolor_by = \"volume\"\n\n[[horizon]]\nstore = \"b\"\n{second}"
        )
    }

    #[test]
    fn an_unknown_color_by_points_at_its_key() {
        let e = error(&two_horizons("opacity = 0.5\n    color_by = \"height\"\n"));
        assert_eq!((e.line, e.column), (11, 5), "{e}");
        assert_eq!(
            e.to_string(),
            "s.toml:11:5: horizon 1: color_by \"height\" is unknown (expected \"constant\", \"depth\" or \"volume\")"
        );
    }

    #[test]
    fn a_horizon_volume_that_names_no_volume_points_at_its_key() {
        let e = error(&two_horizons("color_by = \"volume\"\nvolume = 1\n"));
        assert_eq!((e.line, e.column), (11, 1), "{e}");
        assert_eq!(
            e.to_string(),
            "s.toml:11:1: horizon 1: volume 1 (read by color_by = \"volume\") names no [[volume]]: the scene has 1 [[volume]], numbered from 0"
        );
        // Without volumes the default `volume = 0` names none either: `color_by` is the key.
        let e = error("[[horizon]]\nstore = \"a\"\ncolor = [1, 0, 0]\ncolor_by = \"volume\"\n");
        assert_eq!((e.line, e.column), (4, 1), "{e}");
        assert!(e.message.ends_with("the scene has no [[volume]]"), "{e}");
        // Only `color_by = "volume"` reads it.
        assert!(Scene::parse(Path::new("s.toml"), &two_horizons("volume = 3\n")).is_ok());
    }

    #[test]
    fn an_unknown_horizon_colormap_points_at_its_key() {
        // Refused whatever `color_by` says.
        let e = error(&two_horizons(
            "color_by = \"constant\"\n\tcolormap = \"jet\"\n",
        ));
        assert_eq!((e.line, e.column), (11, 2), "{e}");
        assert!(
            e.to_string().starts_with(
                "s.toml:11:2: horizon 1: colormap: unknown colour map \"jet\" (expected one of seismic,"
            ),
            "{e}"
        );
        let s = Scene::parse(Path::new("s.toml"), &two_horizons("colormap = \"hot_r\"\n"));
        assert_eq!(s.unwrap().horizons[1].colormap, "hot_r");
    }

    #[test]
    fn errors_point_at_line_and_column() {
        let e =
            Scene::parse(Path::new("s.toml"), "[render]\nwidth = 64\nheigth = 3\n").unwrap_err();
        assert_eq!((e.line, e.column), (3, 1), "{e}");
        assert!(e.to_string().starts_with("s.toml:3:1:"), "{e}");
        let e = Scene::parse(Path::new("s.toml"), "[render]\nwidth = \"wide\"\n").unwrap_err();
        assert_eq!(e.line, 2, "{e}");
    }

    #[test]
    fn round_trips_through_toml() {
        let s = Scene::parse(
            Path::new("a.toml"),
            "[[volume]]\nstore = \"/c.strata\"\nwindow = [-1.0, 1.0]\n",
        )
        .unwrap();
        let again = Scene::parse(Path::new("a.toml"), &s.to_toml().unwrap()).unwrap();
        assert_eq!(s, again);
    }
}
