//! The worker engine: frames, feedback → loads → atlas updates, and batch convergence.

use crate::atlas::{PageTable, PlaceError, Pool};
use crate::cache::{CacheStats, Class, PageCache};
use crate::dataset::SceneData;
use crate::feedback::Feedback;
use crate::gpu::backend::{GpuBackend, GpuFrameStats};
use crate::gpu::AdapterChoice;
use crate::horizon::HorFrame;
use crate::raycast::{Bands, CastStats, FrameSetup};
use crate::volume::VolFrame;
use anyhow::{bail, Context, Result};
use std::collections::{HashMap, HashSet};
use std::time::{Duration, Instant};
use strata_common::camera::{default_camera, View};
use strata_common::effects::{EffectSet, Variant};
use strata_common::geo::Affine3;
use strata_common::image::{PartialImage, Rect};
use strata_common::kd::Region;
use strata_common::occlusion::RayLimits;
use strata_common::sample::SampleType;
use strata_common::scene::{Backend, Camera, CodePath, RenderSettings, Scene};

/// How long a batch round waits for its page loads before failing.
pub const LOAD_TIMEOUT: Duration = Duration::from_secs(300);

/// A rendered frame.
pub struct Frame {
    /// The region's premultiplied image.
    pub image: PartialImage,
    /// What its rays asked for.
    pub feedback: Feedback,
    /// Casting counters.
    pub stats: CastStats,
    /// Wall time of the cast.
    pub seconds: f64,
    /// GPU transfer counters (zero on the CPU backend).
    pub gpu: GpuFrameStats,
    /// The frame's effects and the code path that rendered them.
    pub variant: Variant,
    /// The code path in words (see [`Engine::variant_name`]).
    pub variant_name: String,
    /// The CPU caster's feedback and counters per tile (row-major over the image's
    /// rectangle); empty on the GPU backend.
    pub tiles: Vec<crate::raycast::TileOut>,
}

/// What one feedback round did.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct UpdateReport {
    /// Pages requested (with ancestors).
    pub requested: usize,
    /// Requested pages not in the atlas at the start of the round.
    pub missing: usize,
    /// Pages copied into the atlas this round.
    pub uploaded: usize,
    /// Missing pages that found no atlas slot (pool full of needed pages).
    pub no_slot: usize,
}

/// Why a batch render stopped.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub enum Outcome {
    /// Every requested page was resident at its requested level in the last frame.
    Converged,
    /// The round limit was reached first.
    RoundLimit,
    /// The atlas cannot hold every page the view needs at the requested detail.
    AtlasFull,
}

impl Outcome {
    /// The name used in summaries and stats.
    pub fn as_str(self) -> &'static str {
        match self {
            Outcome::Converged => "converged",
            Outcome::RoundLimit => "round-limit",
            Outcome::AtlasFull => "atlas-full",
        }
    }
}

/// Result of a batch render.
pub struct BatchResult {
    /// The final frame's image.
    pub image: PartialImage,
    /// Frames rendered.
    pub rounds: u32,
    /// Why it stopped.
    pub outcome: Outcome,
    /// Casting counters of the final frame.
    pub last: CastStats,
    /// Casting counters summed over all rounds.
    pub total: CastStats,
    /// Time of the final frame's cast. Under selective rounds, where the last round cast
    /// only some tiles, the time a cast of the whole converged frame takes: the last full
    /// round's time, scaled by the converged tiles' thread time against that round's.
    pub last_seconds: f64,
    /// The CPU time a cast of the whole converged frame takes: its tiles' thread CPU time
    /// (each tile as its last cast left it), summed over threads; 0 when no tile was cast
    /// (a region off screen). `None` where nothing times it: [`Engine::tile_cpu_clock`]
    /// off, the GPU backend, or a system without a per-thread clock.
    pub last_cpu_seconds: Option<f64>,
    /// Time spent casting (all rounds).
    pub cast_seconds: f64,
    /// Time spent waiting for loads and updating the atlas.
    pub load_seconds: f64,
    /// Per-round reports.
    pub reports: Vec<UpdateReport>,
    /// Seconds of each round's cast (a selective round's: of the tiles it cast again).
    pub round_cast_seconds: Vec<f64>,
    /// Seconds of each round's loads and atlas update, after its cast.
    pub round_load_seconds: Vec<f64>,
    /// The backend and adapter that rendered (see [`Engine::backend_name`]).
    pub backend: String,
    /// GPU transfer counters of the final frame (zero on the CPU backend).
    pub last_gpu: GpuFrameStats,
    /// Bytes written to the GPU over the batch (pages and tables).
    pub uploaded_bytes: u64,
    /// The final frame's tiles (their feedback, counters and thread time; under selective
    /// rounds, each tile as its last cast left it); empty on the GPU backend.
    pub tiles: Vec<crate::raycast::TileOut>,
    /// The final frame's effects and code path.
    pub variant: Variant,
    /// The final frame's code path in words.
    pub variant_name: String,
}

/// A worker's renderer for one scene.
pub struct Engine {
    /// Render settings (from the scene).
    pub settings: RenderSettings,
    data: SceneData,
    camera: Camera,
    cache: PageCache,
    vpool: Option<Pool>,
    hpool: Option<Pool>,
    tables: Vec<PageTable>,
    /// Pre-integrated tables by (volume, step exponent bits), built on first use: each
    /// costs tens of milliseconds, and a view's exponents rarely change.
    preint: std::sync::Mutex<PreintCache>,
    /// Per volume, its runs of transparent pages (`volume::transparent_runs`), computed on
    /// its first marched frame with skipping: the transfer function is fixed for an engine.
    runs: std::sync::Mutex<std::collections::HashMap<usize, std::sync::Arc<Vec<[u8; 8]>>>>,
    frame_no: u32,
    /// Regions rendered in batch mode so far: a region's first batch converges whatever
    /// `render.rounds_per_frame` says.
    seen_regions: HashSet<[u64; 7]>,
    /// Each region's last first cast (a batch that is not a re-cast) and whether the region
    /// had been seen before it: a re-cast of some of its blocks (cross-worker occlusion's
    /// fix-up, in the same frame) takes the same round budget as the frame's first cast of
    /// that region, not the budget of a seen region, whichever of a worker's leaves was
    /// cast last.
    first_casts: HashMap<[u64; 7], bool>,
    gpu: Option<GpuBackend>,
    /// Effects compiled into every frame's code beyond its own (all of them when
    /// `render.variant = "general"`). The feature-cost benchmark sets single effects here
    /// to measure what each costs a frame that does not use it.
    pub extra_effects: EffectSet,
    /// Time each tile with its thread's CPU clock too ([`BatchResult::last_cpu_seconds`]):
    /// two system calls per tile (about 0.5 µs each here, some 4 ms of CPU per 1024²
    /// frame), so only where a re-split reads it (the worker node sets it); off, the
    /// batch reports no CPU time.
    pub tile_cpu_clock: bool,
}

type PreintCache =
    std::collections::HashMap<(usize, u32), std::sync::Arc<strata_common::tf::PreintTable>>;

/// Why the scene can't go to the GPU caster, if it can't.
fn gpu_unfit(data: &SceneData) -> Option<String> {
    if data.volumes.is_empty() && data.horizons.is_empty() {
        return Some("the scene has no data".into());
    }
    if data.volumes.len() > crate::gpu::MAX_VOLUMES {
        return Some(format!(
            "the GPU caster mixes at most {} volumes",
            crate::gpu::MAX_VOLUMES
        ));
    }
    if data
        .volumes
        .iter()
        .any(|v| v.slices.len() > strata_common::gpu::MAX_SLICES)
    {
        return Some(format!(
            "the GPU caster draws at most {} slices per volume",
            strata_common::gpu::MAX_SLICES
        ));
    }
    if data.horizons.len() > strata_common::gpu::MAX_HORIZONS {
        return Some(format!(
            "the GPU caster intersects at most {} horizons",
            strata_common::gpu::MAX_HORIZONS
        ));
    }
    None
}

/// Opens the GPU backend `render.backend` asks for, or none (the CPU caster).
fn open_backend(s: &RenderSettings, data: &SceneData) -> Result<Option<GpuBackend>> {
    let choice = |allow_software| AdapterChoice {
        adapter: s.gpu_adapter.as_ref().map(|a| a.to_string()),
        allow_software,
        spread: std::env::var(crate::gpu::GPU_SLOT_ENV)
            .ok()
            .and_then(|v| v.parse().ok()),
    };
    let nv = data.volumes.len();
    let types = || {
        data.volumes
            .iter()
            .map(|v| (v.store.header().sample_type, v.store.header().no_data))
            .collect()
    };
    let pyramids = || {
        (0..nv + data.horizons.len())
            .map(|ds| data.pyramid(ds as u16).clone())
            .collect()
    };
    match s.backend {
        Backend::Cpu => Ok(None),
        Backend::Gpu => {
            if s.f64_accumulation {
                bail!(
                    "render.backend = \"gpu\": the GPU caster accumulates in f32, not f64 \
                     (render.f64_accumulation); use \"cpu\" or \"auto\""
                );
            }
            if let Some(why) = gpu_unfit(data) {
                bail!("render.backend = \"gpu\": {why}; use \"cpu\" or \"auto\"");
            }
            GpuBackend::new(&choice(true), pyramids(), types(), s.gpu_filter)
                .map(Some)
                .context("render.backend = \"gpu\"")
        }
        Backend::Auto => {
            if s.f64_accumulation {
                tracing::info!("backend auto: CPU caster (render.f64_accumulation)");
                return Ok(None);
            }
            if let Some(why) = gpu_unfit(data) {
                tracing::info!("backend auto: CPU caster ({why})");
                return Ok(None);
            }
            match GpuBackend::new(&choice(false), pyramids(), types(), s.gpu_filter) {
                Ok(g) => Ok(Some(g)),
                Err(e) => {
                    tracing::info!("backend auto: CPU caster ({e:#})");
                    Ok(None)
                }
            }
        }
    }
}

/// The element type of the CPU caster's volume slots: the volumes' own sample type when
/// `render.compact_slots` is on, they all share one and none has a no-data value (the NaN of
/// a decoded page has no integer to go to), else f32.
fn cpu_slot_type(s: &RenderSettings, data: &SceneData) -> SampleType {
    let first = data.volumes[0].store.header().sample_type;
    let compact = s.compact_slots
        && data.volumes.iter().all(|v| {
            let h = v.store.header();
            h.sample_type == first && h.no_data.is_none()
        });
    if compact {
        first
    } else {
        SampleType::F32
    }
}

fn rows_f32(a: &Affine3) -> ([[f32; 3]; 3], [f32; 3]) {
    let m = [0, 1, 2].map(|r| [0, 1, 2].map(|c| a.rows[r][c] as f32));
    let c = [0, 1, 2].map(|r| a.rows[r][3] as f32);
    (m, c)
}

/// Distance from the eye at which level `l` becomes fine enough: where one pixel covers
/// `2^l` samples of size `size` within the tolerance `tau` (level 0 from the eye on).
fn level_distances(size: f64, levels: usize, tau: f64, pixel_angle: f32) -> Vec<f32> {
    (0..levels)
        .map(|l| {
            if l == 0 {
                0.0
            } else {
                (size * (1u64 << l) as f64 / (tau * pixel_angle as f64)) as f32
            }
        })
        .collect()
}

fn col_len(a: &Affine3, c: usize) -> f64 {
    (0..3).map(|r| a.rows[r][c].powi(2)).sum::<f64>().sqrt()
}

impl Engine {
    /// Opens the scene's stores, sizes the cache and the atlas pools, and pins every data
    /// set's root page so each page table always has a fallback.
    pub fn new(scene: &Scene) -> Result<Self> {
        let s = scene.render.clone();
        validate(&s)?;
        let data = SceneData::open(scene)?;
        let cache = PageCache::new(
            data.stores(),
            s.cache_mb.saturating_mul(1 << 20),
            s.loader_threads as usize,
        );
        let vps = data.volumes.first().map(|v| v.pyramid.page_samples());
        for v in &data.volumes {
            if v.pyramid.page_samples() != vps.unwrap() {
                bail!(
                    "{}: all volumes of a scene must share one brick size (the atlas has one slot size)",
                    v.store.path().display()
                );
            }
        }
        let hps = data.horizons.first().map(|h| h.pyramid.page_samples());
        for h in &data.horizons {
            if h.pyramid.page_samples() != hps.unwrap() {
                bail!(
                    "{}: all horizons of a scene must share one tile size",
                    h.store.path().display()
                );
            }
        }
        let mut gpu = open_backend(&s, &data)?;
        let vpool = match (vps, gpu.as_mut()) {
            (None, _) => None,
            (Some(n), None) => {
                cpu_atlas_fits("atlas_mb", s.atlas_mb)?;
                let t = cpu_slot_type(&s, &data);
                let page = data.volumes[0].pyramid.page() as usize;
                let pool = Pool::typed(n, s.atlas_mb.saturating_mul(1 << 20), t);
                tracing::debug!(
                    slot_type = ?t,
                    slots = pool.capacity(),
                    macrocells = s.macrocells && s.empty_space_skipping,
                    "CPU volume atlas"
                );
                Some(if s.macrocells && s.empty_space_skipping {
                    pool.with_cells(page)
                } else {
                    pool
                })
            }
            (Some(n), Some(g)) => {
                // The samples live in one device buffer in their own width (8-bit data takes
                // a byte per sample): as many slots as the budget and the adapter's largest
                // binding allow.
                let (want, slots) = g.volume_slots(n, s.atlas_mb.saturating_mul(1 << 20));
                if slots < want {
                    tracing::warn!(
                        want,
                        slots,
                        "render.atlas_mb exceeds the adapter's largest storage binding"
                    );
                }
                g.alloc_pool(slots, n)?;
                Some(Pool::bookkeeping(n, slots))
            }
        };
        // Both kinds of pool mark fragmented tiles in the page tables both casters read.
        let side = data
            .horizons
            .first()
            .map_or(0, |h| h.pyramid.page() as usize);
        let hpool = match (hps, gpu.as_mut()) {
            (None, _) => None,
            (Some(n), None) => {
                cpu_atlas_fits("horizon_atlas_mb", s.horizon_atlas_mb)?;
                Some(Pool::new(n, s.horizon_atlas_mb.saturating_mul(1 << 20)).with_tiles(side))
            }
            (Some(n), Some(g)) => {
                let slots = Pool::slots_for(n, s.horizon_atlas_mb.saturating_mul(1 << 20))
                    .min(g.max_horizon_slots(n));
                g.alloc_horizon_pool(slots, n)?;
                Some(Pool::bookkeeping(n, slots).with_tiles(side))
            }
        };
        let tables = (0..data.volumes.len() + data.horizons.len())
            .map(|ds| PageTable::new(data.pyramid(ds as u16)))
            .collect();
        let camera = match &scene.camera {
            Some(c) => c.clone(),
            None => default_camera(&data.bounds(), &s),
        };
        let mut e = Engine {
            data,
            camera,
            cache,
            vpool,
            hpool,
            tables,
            preint: Default::default(),
            runs: Default::default(),
            tile_cpu_clock: false,
            frame_no: 0,
            seen_regions: HashSet::new(),
            first_casts: HashMap::new(),
            extra_effects: match s.variant {
                CodePath::Specialised => EffectSet::NONE,
                CodePath::General => EffectSet::ALL,
            },
            settings: s,
            gpu,
        };
        if let Some(g) = &e.gpu {
            tracing::info!(
                adapter = %g.adapter_name(),
                pool_bits = g.pool_format().bits,
                filter = ?g.filter(),
                "GPU caster"
            );
        }
        e.pin_roots()?;
        Ok(e)
    }

    fn pin_roots(&mut self) -> Result<()> {
        let none = HashSet::new();
        let n = self.data.volumes.len() + self.data.horizons.len();
        for ds in 0..n as u16 {
            let p = self.data.pyramid(ds).clone();
            let top = p.level_count() - 1;
            let key = p.id(top, [0, 0, 0]).with_dataset(ds).0;
            let page = self.cache.load_now(key)?;
            let key_name = if (ds as usize) < self.data.volumes.len() {
                "render.atlas_mb"
            } else {
                "render.horizon_atlas_mb"
            };
            self.place(ds, key, &page, 0, true, &none).map_err(|_| {
                anyhow::anyhow!("the atlas has no slot for the root pages; raise {key_name}")
            })?;
        }
        self.rebuild_tables();
        Ok(())
    }

    /// Puts a page into its pool (and the GPU's copy); a volume page's macrocells are
    /// classified against its volume's transfer function.
    fn place(
        &mut self,
        ds: u16,
        key: u64,
        page: &[f32],
        frame: u32,
        pinned: bool,
        keep: &HashSet<u64>,
    ) -> Result<u32, PlaceError> {
        let volume = self.is_volume(ds);
        let pool = if volume {
            self.vpool.as_mut().expect("volume pool")
        } else {
            self.hpool.as_mut().expect("horizon pool")
        };
        let slot = pool.place(key, page, frame, pinned, keep)?;
        if volume {
            let tf = &self.data.volumes[ds as usize].tf;
            pool.classify(slot, |lo, hi| tf.max_alpha(lo, hi) > 0.0);
        }
        if let Some(g) = self.gpu.as_mut() {
            g.write_page(ds, slot, page);
        }
        Ok(slot)
    }

    fn is_volume(&self, ds: u16) -> bool {
        (ds as usize) < self.data.volumes.len()
    }

    fn pool_mut(&mut self, ds: u16) -> &mut Pool {
        if self.is_volume(ds) {
            self.vpool.as_mut().unwrap()
        } else {
            self.hpool.as_mut().unwrap()
        }
    }

    fn pool(&self, ds: u16) -> &Pool {
        if self.is_volume(ds) {
            self.vpool.as_ref().unwrap()
        } else {
            self.hpool.as_ref().unwrap()
        }
    }

    fn rebuild_tables(&mut self) {
        for ds in 0..self.tables.len() as u16 {
            let pyr = self.data.pyramid(ds).clone();
            let pool = if (ds as usize) < self.data.volumes.len() {
                self.vpool.as_ref().unwrap()
            } else {
                self.hpool.as_ref().unwrap()
            };
            let lookup = pool.resident_of(ds, &pyr);
            self.tables[ds as usize].rebuild(lookup);
        }
        if let Some(g) = self.gpu.as_mut() {
            g.sync_tables(&self.tables);
        }
    }

    /// The backend that renders, e.g. `cpu (16 threads)` or
    /// `gpu: NVIDIA H100 80GB HBM3 (Vulkan)`.
    pub fn backend_name(&self) -> String {
        match &self.gpu {
            Some(g) if g.filter() == strata_common::scene::GpuFilter::Hardware => {
                format!("gpu: {}, hardware filter", g.adapter_name())
            }
            Some(g) => format!("gpu: {}", g.adapter_name()),
            None => format!("cpu ({} threads)", rayon::current_num_threads()),
        }
    }

    /// The most pixels the GPU backend casts in one dispatch (`None` on the CPU); a larger
    /// region is cast in bands.
    pub fn gpu_max_frame_pixels(&self) -> Option<u64> {
        self.gpu.as_ref().map(|g| g.max_frame_pixels())
    }

    /// Caps the pixels the GPU backend casts in one band below the adapter's limit (`None`:
    /// the adapter's), so that tests band frames of any size. No effect on the CPU.
    pub fn set_gpu_band_pixels(&mut self, cap: Option<u64>) {
        if let Some(g) = self.gpu.as_mut() {
            g.set_band_pixels(cap);
        }
    }

    /// Test hook: makes the GPU backend raise a real wgpu validation error outside any
    /// cast (a write past a buffer's end), which the next readback reports. No effect on
    /// the CPU.
    #[doc(hidden)]
    pub fn gpu_raise_an_error(&mut self) {
        if let Some(g) = self.gpu.as_mut() {
            g.write_past_a_buffer();
        }
    }

    /// Test hook: makes the GPU backend's image buffer an allocation the device refuses;
    /// true if it did. False on the CPU.
    #[doc(hidden)]
    pub fn gpu_fail_an_allocation(&mut self) -> bool {
        self.gpu.as_mut().is_some_and(|g| g.fail_an_allocation())
    }

    /// Bytes of the GPU backend's image buffer (`None` on the CPU, 0 before a frame).
    #[doc(hidden)]
    pub fn gpu_image_buffer_bytes(&self) -> Option<u64> {
        self.gpu.as_ref().map(|g| g.image_buffer_bytes())
    }

    /// Regions the GPU backend cast in more than one band (`None` on the CPU).
    pub fn gpu_banded_regions(&self) -> Option<u64> {
        self.gpu.as_ref().map(|g| g.banded_regions())
    }

    /// Bits per sample of the GPU's volume pool (8, 16 or 32; `None` on the CPU).
    pub fn gpu_pool_bits(&self) -> Option<u32> {
        self.gpu
            .as_ref()
            .filter(|_| !self.data.volumes.is_empty())
            .map(|g| g.pool_format().bits)
    }

    /// The camera (the scene's, or one that frames the data).
    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// World bounds of the scene's data.
    pub fn bounds(&self) -> Region {
        self.data.bounds()
    }

    /// The region that holds the whole scene (bounds padded so no sample lies on its faces).
    pub fn scene_region(&self) -> Region {
        self.data.region()
    }

    /// The view of the scene camera at `width`×`height`.
    pub fn view(&self, width: u32, height: u32) -> Result<View> {
        Ok(View::new(&self.camera, &self.settings, width, height)?)
    }

    /// Page-cache counters.
    pub fn cache_stats(&self) -> CacheStats {
        self.cache.stats()
    }

    /// Bytes of the CPU volume atlas per voxel of a slot (1 for compact `u8` slots, 4 for
    /// f32; `None` on the GPU backend or without volumes).
    pub fn cpu_atlas_bytes_per_voxel(&self) -> Option<usize> {
        let p = self.vpool.as_ref().filter(|_| self.gpu.is_none())?;
        Some(p.slot_bytes() / p.page_samples)
    }

    /// Atlas slots in use (volume pool, horizon pool).
    pub fn atlas_usage(&self) -> (usize, usize) {
        (
            self.vpool.as_ref().map_or(0, |p| p.used()),
            self.hpool.as_ref().map_or(0, |p| p.used()),
        )
    }

    /// Prepares the per-frame structures for `region` seen through `view`.
    fn setup<'a>(
        &'a self,
        view: &View,
        region: &Region,
        limits: Option<RayLimits<'a>>,
    ) -> FrameSetup<'a> {
        let s = &self.settings;
        let pa = view.pixel_angle;
        // Finest voxel spacing of all volumes in display units: the step's reference (each
        // volume's opacity takes its own spacing, below).
        let mut vmin = f64::INFINITY;
        let mut max_levels = 1;
        let mut vols = Vec::new();
        let tf_tables_for = |exps: &[f32], tf: &strata_common::tf::TransferFunction| {
            exps.iter().map(|&e| tf.step_table(e)).collect::<Vec<_>>()
        };
        let rel: Vec<Affine3> = self
            .data
            .volumes
            .iter()
            .map(|v| view.relative_affine(&v.to_world))
            .collect();
        for a in &rel {
            for c in 0..3 {
                vmin = vmin.min(col_len(a, c));
            }
        }
        for v in &self.data.volumes {
            max_levels = max_levels.max(v.pyramid.level_count());
        }
        // Bands: the step doubles where the pixel footprint covers twice the finest voxel.
        let nb = if s.adaptive_step && !self.data.volumes.is_empty() {
            max_levels.min(8)
        } else {
            1
        };
        let base = (s.step * vmin) as f32;
        let mut bands = Bands {
            start: vec![0.0],
            dt: vec![base],
        };
        for b in 1..nb {
            let start = (vmin * (1u64 << b) as f64 / (s.tau * pa as f64)) as f32;
            bands.start.push(band_start(start, bands.dt[b - 1]));
            bands.dt.push(base * (1u64 << b) as f32);
        }
        for (i, v) in self.data.volumes.iter().enumerate() {
            // Each volume's opacities are per its own finest voxel spacing (as ParaView's
            // per-representation opacity unit distance defaults to the data's spacing), so a
            // volume looks the same whatever other volumes share the scene: the step
            // exponent of band b is its step over that spacing. (For the finest volume, and
            // a volume alone, `vmin / own` is exactly 1.)
            let own = (0..3)
                .map(|k| col_len(&rel[i], k))
                .fold(f64::INFINITY, f64::min);
            let exps: Vec<f32> = (0..nb)
                .map(|b| ((s.step * (vmin / own)) as f32) * (1u64 << b) as f32)
                .collect();
            let inv = rel[i]
                .inverse()
                .expect("stores are refused at open unless invertible with scales in 1e-30..1e30, z_scale in 1e-6..1e6");
            let (m, c) = rows_f32(&inv);
            let vsize = (0..3).map(|k| col_len(&rel[i], k)).fold(0.0, f64::max);
            let nl = v.pyramid.level_count();
            let level_t = level_distances(vsize, nl, s.tau, pa);
            let transparent: Vec<bool> = v
                .bounds
                .iter()
                .map(|&b| v.tf.page_transparent(b, s.empty_space_skipping))
                .collect();
            let d = v.dims();
            let pool = self.vpool.as_ref().unwrap();
            let tables = tf_tables_for(&exps, &v.tf);
            let invisible = s.empty_space_skipping && transparent.iter().all(|&t| t);
            // A volume its transfer function hides is never marched: no tables (and the
            // GPU pipeline, which has no pre-integration then, is not asked for them).
            let pre = (s.preintegrated && !invisible).then(|| {
                let mut cache = self.preint.lock().unwrap_or_else(|e| e.into_inner());
                exps.iter()
                    .map(|&e| {
                        cache
                            .entry((i, e.to_bits()))
                            .or_insert_with(|| std::sync::Arc::new(v.tf.preintegrated_table(e)))
                            .clone()
                    })
                    .collect()
            });
            let cells = pool
                .cells()
                .filter(|_| s.empty_space_skipping && s.macrocells);
            vols.push(VolFrame {
                ds: v.ds,
                m,
                c,
                hi: [0, 1, 2].map(|k| d[k] as f32 - 0.5),
                level_t,
                core: v.pyramid.core() as f32,
                border: v.pyramid.border() as f32,
                page: v.pyramid.page() as usize,
                table: &self.tables[v.ds as usize],
                pool,
                samples: pool.samples(),
                cells: cells.map(|c| c.visible()),
                reach: cells.map(|c| c.reach()),
                cells_per_axis: cells.map_or(0, |c| c.per_axis()),
                invisible,
                transparent_runs: if s.empty_space_skipping && !invisible {
                    let mut runs = self.runs.lock().unwrap_or_else(|e| e.into_inner());
                    runs.entry(i)
                        .or_insert_with(|| {
                            std::sync::Arc::new(crate::volume::transparent_runs(
                                &self.tables[v.ds as usize],
                                &transparent,
                            ))
                        })
                        .clone()
                } else {
                    Default::default()
                },
                transparent,
                flat: crate::packet::FlatTables::new(&tables),
                tables,
                pre,
                page_keys: &v.page_keys,
                slices: &v.slices,
                tf: &v.tf,
            });
        }
        let mut hors = Vec::new();
        for h in &self.data.horizons {
            let rel = view.relative_affine(&h.to_world);
            let inv = rel
                .inverse()
                .expect("stores are refused at open unless invertible with scales in 1e-30..1e30, z_scale in 1e-6..1e6");
            let (m, c) = rows_f32(&inv);
            let cell = col_len(&rel, 0).max(col_len(&rel, 1));
            let nl = h.pyramid.level_count();
            let level_t = level_distances(cell, nl, s.tau, pa);
            let d = h.pyramid.level(0).dims;
            hors.push(HorFrame {
                ds: h.ds,
                m,
                c,
                dims: [d[0] as u32, d[1] as u32],
                level_t,
                core: h.pyramid.core(),
                border: h.pyramid.border(),
                page: h.pyramid.page() as usize,
                table: &self.tables[h.ds as usize],
                pool: self.hpool.as_ref().unwrap(),
                bounds: &h.bounds,
                boxes: &h.boxes,
                // A surface coloured by a volume is shaded white; the caster multiplies
                // the volume's colour in at each hit.
                color: if h.attribute.is_some() {
                    [1.0; 3]
                } else {
                    h.color
                },
                depth_map: h.depth_map.as_ref().map(|(m, r)| (m, *r)),
                attribute: h.attribute.map(|v| (v, h.color)),
                opacity: h.opacity,
                lighting: s.lighting,
                pyramid: &h.pyramid,
            });
        }
        // Region ∩ data bounds, camera-relative.
        let data = self.data.region();
        let clipped = Region {
            lo: [0, 1, 2].map(|a| region.lo[a].max(data.lo[a])),
            hi: [0, 1, 2].map(|a| region.hi[a].min(data.hi[a])),
        };
        let (rlo, rhi) = view.display.region(region);
        let region_lo = [0, 1, 2].map(|a| (rlo[a] - view.eye[a]) as f32);
        let region_hi = [0, 1, 2].map(|a| (rhi[a] - view.eye[a]) as f32);
        // A re-cast of some blocks casts (and allocates) only the part of the region's
        // rectangle that holds them: the rest of a tile grid over the whole rectangle cost
        // about 1 ms a call on the demo at 1280×720, for a handful of blocks. Each pixel's
        // ray is the same either way.
        let rect = match limits.and_then(|l| l.only) {
            Some(m) => m
                .pixel_bounds()
                .map_or(Rect::EMPTY, |b| screen_rect(view, &clipped).intersect(&b)),
            None => screen_rect(view, &clipped),
        };
        let vols_n = vols.len();
        let one_invisible = vols_n == 1 && vols[0].invisible;
        let all_invisible = vols.iter().all(|v| v.invisible);
        // The packets' gathers index with i32 (an atlas of 2 G elements or more, e.g. 8 GiB
        // of f32 slots, takes the scalar march).
        let packet_indices_fit = vols
            .iter()
            .all(|v| v.samples.len() < i32::MAX as usize && v.flat.rgba.len() < i32::MAX as usize);
        let marched = !all_invisible;
        let effects = EffectSet::NONE
            .with_if(EffectSet::VOLUME, marched)
            .with_if(EffectSet::VOLUMES, marched && vols_n > 1)
            .with_if(EffectSet::HORIZONS, !hors.is_empty())
            .with_if(EffectSet::LIGHTING, hors.iter().any(|h| h.lighting))
            .with_if(EffectSet::SLICES, vols.iter().any(|v| !v.slices.is_empty()))
            .with_if(EffectSet::SHADING, marched && s.volume_shading)
            .with_if(
                EffectSet::PREINTEGRATED,
                marched && vols.iter().any(|v| v.pre.is_some()),
            );
        FrameSetup {
            width: view.width,
            height: view.height,
            dir00: view.dir00,
            du: view.du,
            dv: view.dv,
            tiles: view.tiles,
            region_lo,
            region_hi,
            rect,
            vols,
            hors,
            bands,
            ert: (s.early_termination as f32).min(1.0),
            volume_shading: s.volume_shading,
            // (A single volume invisible under its transfer function is never marched.)
            packets: s.simd
                && vols_n == 1
                && !one_invisible
                && packet_indices_fit
                && !s.volume_shading
                && !s.preintegrated
                && !s.f64_accumulation
                && crate::packet::available(),
            lanes: crate::packet::lanes_for(s.simd_lanes),
            // 1024 base steps: with the packets' lockstep step a lane's samples cost less
            // than its set-up, so deeper chunks pay (bonsai 1024², 2 threads, side by side:
            // 32 → 128 base steps 0.83× the time, → 256 0.82×, → 1024 0.78×; the
            // translucent demo volume 0.97× from 128 to 1024). A tile's packets
            // still go front to back together. With no volume to march (only surfaces and
            // slices) the rays go in one piece.
            chunk: if base > 0.0 && base.is_finite() && !all_invisible {
                1024.0 * base
            } else {
                f32::INFINITY
            },
            limits,
            only_tiles: None,
            on_tile: None,
            cpu_clock: self.tile_cpu_clock,
            // f64 accumulation has one copy of the caster: the general one.
            variant: Variant::new(
                effects,
                if s.f64_accumulation {
                    EffectSet::ALL
                } else {
                    self.extra_effects
                },
            ),
            f64_accumulation: s.f64_accumulation,
        }
    }

    /// The code path of a frame in words: `specialised`, `general` or
    /// `specialised+EFFECTS`, then the effects compiled in, then how the CPU marched
    /// (`simd` packets of 8 lanes, `simd16` of 16, or `scalar`) or the GPU pipeline's
    /// effects, e.g. `specialised [volume+horizons] simd16`. `lanes` is 0 without packets.
    pub fn variant_name(&self, v: Variant, lanes: usize) -> String {
        let how = match &self.gpu {
            Some(_) => format!(
                "gpu pipeline [{}]",
                crate::gpu::pipeline_effects(v.compiled)
            ),
            None if lanes == 8 => "simd".into(),
            None if lanes > 0 => format!("simd{lanes}"),
            None if self.settings.f64_accumulation => "scalar f64".into(),
            None => "scalar".into(),
        };
        format!("{} [{}] {how}", v.path_name(), v.compiled)
    }

    /// The sampling bands a frame of `region` through `view` uses: `(start, step)` per band.
    pub fn sampling_bands(&self, view: &View, region: &Region) -> (Vec<f32>, Vec<f32>) {
        let b = self.setup(view, region, None).bands;
        (b.start, b.dt)
    }

    /// Renders one frame of `region` with what is resident now, on the engine's backend.
    pub fn render_frame(&mut self, view: &View, region: &Region) -> Result<Frame> {
        self.render_frame_limited(view, region, None)
    }

    /// [`Engine::render_frame`] under cross-worker occlusion: each ray with the termination
    /// threshold `limits` gives its block, and rays it leaves out not cast at all (their
    /// pixels stay transparent and they ask for no page).
    pub fn render_frame_limited(
        &mut self,
        view: &View,
        region: &Region,
        limits: Option<RayLimits<'_>>,
    ) -> Result<Frame> {
        self.render_frame_tiles(view, region, limits, None, false)
    }

    /// [`Engine::render_frame_limited`], casting only the tiles `only` marks on the CPU
    /// ([`FrameSetup::only_tiles`]; the GPU casts every pixel). With `early_loads`, the
    /// pages a tile lacks are asked of the cache as soon as it is cast (batch rounds only:
    /// a single frame, such as occlusion's first pass or an interactive frame, loads
    /// nothing it was not asked to).
    fn render_frame_tiles(
        &mut self,
        view: &View,
        region: &Region,
        limits: Option<RayLimits<'_>>,
        only: Option<&[bool]>,
        early_loads: bool,
    ) -> Result<Frame> {
        let t = Instant::now();
        if let Some(mut gpu) = self.gpu.take() {
            let setup = self.setup(view, region, limits);
            let res = gpu.render(&setup);
            let variant = setup.variant;
            drop(setup);
            self.gpu = Some(gpu);
            let (image, feedback, stats, g) = res?;
            return Ok(Frame {
                image,
                feedback,
                stats,
                seconds: t.elapsed().as_secs_f64(),
                gpu: g,
                variant,
                variant_name: self.variant_name(variant, 0),
                tiles: Vec::new(),
            });
        }
        // Pages a tile lacks start loading (as prefetches: they fill only free cache space
        // and evict nothing) while the other tiles are cast; the round's update then finds
        // them loaded or in flight. The frame's pixels do not depend on it: the atlas
        // changes only in `update`.
        let early = |entries: &[crate::feedback::FeedbackEntry]| {
            for e in entries.iter().filter(|e| !self.in_atlas(e.page)) {
                self.cache.request(e.page, Class::Prefetch, 1.0);
            }
        };
        let mut setup = self.setup(view, region, limits);
        setup.only_tiles = only;
        if early_loads {
            setup.on_tile = Some(&early);
        }
        let (variant, lanes) = (setup.variant, if setup.packets { setup.lanes } else { 0 });
        let out = setup.render();
        drop(setup);
        Ok(Frame {
            image: out.image,
            feedback: feedback_of(&out.tiles),
            stats: out.stats,
            seconds: t.elapsed().as_secs_f64(),
            gpu: GpuFrameStats::default(),
            variant,
            variant_name: self.variant_name(variant, lanes),
            tiles: out.tiles,
        })
    }

    /// The tiles of `f` to cast again after this round's loads: those whose rays asked for
    /// a page that is not in the atlas now (before the loads). Every other tile had each
    /// page it wanted, at the level it wanted, so casting it again gives the same pixels.
    /// `None` where the frame has no tiles (the GPU backend).
    fn tiles_missing_pages(&self, f: &Frame) -> Option<Vec<bool>> {
        if f.tiles.is_empty() {
            return None;
        }
        Some(
            f.tiles
                .iter()
                .map(|t| t.feedback.iter().any(|e| !self.in_atlas(e.page)))
                .collect(),
        )
    }

    /// Whether page `key` has a slot in its pool's atlas now.
    fn in_atlas(&self, key: u64) -> bool {
        let ds = strata_common::ids::PageId(key).dataset();
        self.pool(ds).slot_of(key).is_some()
    }

    fn parent_key(&self, key: u64) -> Option<u64> {
        let id = strata_common::ids::PageId(key);
        let ds = id.dataset();
        let p = self.data.pyramid(ds);
        let l = id.level() as usize;
        let b = p.brick_of(id.morton());
        p.parent(l, b).map(|pb| p.id(l + 1, pb).with_dataset(ds).0)
    }

    /// Turns a frame's feedback into loads and atlas updates. With `wait`, blocks until the
    /// real requests are loaded (batch mode); otherwise uploads what is already cached
    /// (interactive mode) and leaves the rest to the loader threads.
    pub fn update(&mut self, fb: &Feedback, wait: bool) -> Result<UpdateReport> {
        self.frame_no += 1;
        let frame = self.frame_no;
        let prio = fb.priorities(|k| self.parent_key(k));
        let needed: HashSet<u64> = prio.iter().map(|e| e.0).collect();
        let mut missing = Vec::new();
        for &(k, c) in &prio {
            let ds = strata_common::ids::PageId(k).dataset();
            if self.pool(ds).slot_of(k).is_some() {
                self.pool_mut(ds).touch(k, frame);
            } else {
                missing.push((k, c));
            }
        }
        let mut report = UpdateReport {
            requested: prio.len(),
            missing: missing.len(),
            ..UpdateReport::default()
        };
        if missing.is_empty() {
            return Ok(report);
        }
        // This round loads and uploads at most the per-frame budget, most important first
        // (the rest is asked for again by the next frame's feedback). The round's pages are
        // locked in the cache for the length of this update (loaded, then copied into the
        // atlas), so they must fit the cache's byte budget together: the atlas's room does
        // not bound them, as the atlas may hold pages in their stored width (u8: a quarter
        // of the cache's f32), and a cold round of a u8 survey at the defaults had locked
        // twice `cache_mb`. At least one page a round, whatever the budget.
        let budget = self.settings.upload_pages_per_frame.max(1) as usize;
        let cache_budget = self.cache.budget();
        let mut locked = 0u64;
        // Only pages their pool has room for (free slots, or slots of pages this frame does
        // not need): a pool full of needed pages must not take the round's places from the
        // other pool's pages (the round would upload nothing and end the batch as
        // atlas-full while the other pool had room), nor be read from disk for nothing.
        let mut room = [true, false].map(|volume| {
            let pool = if volume { &self.vpool } else { &self.hpool };
            pool.as_ref().map_or(0, |p| p.room(&needed))
        });
        let mut round: Vec<(u64, u32)> = Vec::with_capacity(budget.min(missing.len()));
        for &(k, c) in &missing {
            if round.len() >= budget {
                break;
            }
            let ds = strata_common::ids::PageId(k).dataset();
            let r = &mut room[!self.is_volume(ds) as usize];
            if *r == 0 {
                report.no_slot += 1;
                continue;
            }
            let bytes = self.cache.page_bytes(k);
            if !round.is_empty() && locked + bytes > cache_budget {
                break;
            }
            locked += bytes;
            *r -= 1;
            round.push((k, c));
        }
        self.cache.set_locked(round.iter().map(|e| e.0));
        self.cache.cancel_prefetch();
        let maxc = round.iter().map(|e| e.1).max().unwrap_or(1).max(1) as f32;
        for &(k, c) in &round {
            self.cache.request(k, Class::Real, c as f32 / maxc);
        }
        if wait {
            if let Err(e) = self.cache.wait_real(LOAD_TIMEOUT) {
                // Unlocked on the way out too: the round's pages would otherwise stay
                // unevictable until the next update.
                self.cache.set_locked(std::iter::empty());
                anyhow::bail!("loading pages: {e}");
            }
        }
        for &(k, _) in &round {
            if report.uploaded >= budget {
                break;
            }
            let Some(page) = self.cache.get(k) else {
                continue;
            };
            let ds = strata_common::ids::PageId(k).dataset();
            match self.place(ds, k, &page, frame, false, &needed) {
                Ok(_) => report.uploaded += 1,
                Err(PlaceError::Full) => report.no_slot += 1,
            }
        }
        self.cache.set_locked(std::iter::empty());
        // Prefetch: the children of the most-covered requested pages, into free cache space
        // only (they never evict anything and never outrank a real request).
        let free = self.cache.budget().saturating_sub(self.cache.bytes());
        if free > 0 {
            let mut n = 0;
            for &(k, c) in prio.iter().take(64) {
                let id = strata_common::ids::PageId(k);
                let l = id.level() as usize;
                if l == 0 || !fb.coverage.contains_key(&k) {
                    continue;
                }
                let p = self.data.pyramid(id.dataset());
                for ch in p.children(l, p.brick_of(id.morton())) {
                    let ck = p.id(l - 1, ch).with_dataset(id.dataset()).0;
                    self.cache
                        .request(ck, Class::Prefetch, c as f32 / maxc * 0.5);
                    n += 1;
                }
                if n > 256 {
                    break;
                }
            }
        }
        self.rebuild_tables();
        Ok(report)
    }

    /// Batch mode: frame → feedback → load, repeated until every page the last frame asked
    /// for was resident at its requested level (converged) or `render.max_rounds` is hit
    /// (`render.rounds_per_frame` when set, for a region this engine rendered before).
    pub fn render_batch(&mut self, view: &View, region: &Region) -> Result<BatchResult> {
        self.render_batch_limited(view, region, None)
    }

    /// [`Engine::render_batch`] under cross-worker occlusion
    /// ([`Engine::render_frame_limited`]): the batch converges on the pages the rays cast
    /// ask for.
    pub fn render_batch_limited(
        &mut self,
        view: &View,
        region: &Region,
        limits: Option<RayLimits<'_>>,
    ) -> Result<BatchResult> {
        // A region at an image size (occlusion's low-resolution first pass does not count
        // as the frame's first batch).
        let key = [0, 1, 2, 3, 4, 5, 6].map(|i| match i {
            0..3 => region.lo[i].to_bits(),
            3..6 => region.hi[i - 3].to_bits(),
            _ => (view.width as u64) << 32 | view.height as u64,
        });
        // (Bounded: regions and sizes come from the network; forgetting them only costs
        // a region its first-frame rounds again.)
        if self.seen_regions.len() >= 4096 {
            self.seen_regions.clear();
            self.first_casts.clear();
        }
        let recast = limits.as_ref().is_some_and(|l| l.only.is_some());
        let seen = match self.first_casts.get(&key) {
            Some(&seen) if recast => seen,
            _ => {
                let seen = !self.seen_regions.insert(key);
                self.first_casts.insert(key, seen);
                seen
            }
        };
        let rpf = self.settings.rounds_per_frame;
        let max_rounds = if seen && rpf > 0 {
            rpf.min(self.settings.max_rounds)
        } else {
            self.settings.max_rounds
        }
        .max(1);
        let mut reports = Vec::new();
        let mut total = CastStats::default();
        let (mut cast_s, mut load_s) = (0.0, 0.0);
        let (mut round_cast, mut round_load) = (Vec::new(), Vec::new());
        let mut rounds = 0;
        let mut uploaded_bytes = 0;
        // The last round's frame and the tiles to cast again (selective rounds).
        let mut last: Option<(Frame, Vec<bool>)> = None;
        // The last round that cast every tile: its wall time and its tiles' thread time.
        let mut full: Option<(f64, f64)> = None;
        let early = self.settings.early_loads;
        loop {
            rounds += 1;
            let only = last.as_ref().map(|(_, m)| m.as_slice());
            let cast_all = only.is_none();
            let mut f = self.render_frame_tiles(view, region, limits, only, early)?;
            if cast_all {
                full = Some((f.seconds, f.tiles.iter().map(|t| t.seconds).sum()));
            }
            cast_s += f.seconds;
            round_cast.push(f.seconds);
            uploaded_bytes += f.gpu.uploaded_bytes;
            total += f.stats;
            if let Some((prev, mask)) = last.take() {
                keep_tiles(&mut f, prev, &mask)?;
            }
            let again = if self.settings.selective_rounds {
                self.tiles_missing_pages(&f)
            } else {
                None
            };
            let t = Instant::now();
            let rep = self.update(&f.feedback, true).context("batch round")?;
            let loads = t.elapsed().as_secs_f64();
            load_s += loads;
            round_load.push(loads);
            let outcome = if rep.missing == 0 {
                Some(Outcome::Converged)
            } else if rep.uploaded == 0 && rep.no_slot > 0 {
                Some(Outcome::AtlasFull)
            } else if rounds >= max_rounds {
                Some(Outcome::RoundLimit)
            } else {
                None
            };
            tracing::debug!(
                round = rounds,
                requested = rep.requested,
                missing = rep.missing,
                uploaded = rep.uploaded,
                effects = %f.variant.effects,
                variant = %f.variant_name,
                "feedback round"
            );
            reports.push(rep);
            if outcome.is_none() {
                if let Some(mask) = again {
                    last = Some((f, mask));
                    continue;
                }
            }
            if let Some(outcome) = outcome {
                // The last round's update wrote after its cast: its pages and tables are
                // this batch's too (the next batch's first cast had counted them).
                uploaded_bytes += self.gpu.as_mut().map_or(0, GpuBackend::take_uploaded);
                return Ok(BatchResult {
                    image: f.image,
                    rounds,
                    outcome,
                    last: f.stats,
                    total,
                    last_seconds: match full {
                        // The last round cast only some tiles: the time of a whole cast of
                        // the converged tiles is the last full round's wall time scaled by
                        // their thread time against that round's (which keeps its set-up,
                        // its parallel efficiency and its threads).
                        Some((wall, busy)) if !cast_all && busy > 0.0 => {
                            wall * f.tiles.iter().map(|t| t.seconds).sum::<f64>() / busy
                        }
                        _ => f.seconds,
                    },
                    last_cpu_seconds: (self.tile_cpu_clock
                        && self.gpu.is_none()
                        && crate::raycast::thread_cpu_seconds().is_some())
                    .then(|| f.tiles.iter().map(|t| t.cpu_seconds).sum()),
                    cast_seconds: cast_s,
                    load_seconds: load_s,
                    reports,
                    round_cast_seconds: round_cast,
                    round_load_seconds: round_load,
                    backend: self.backend_name(),
                    last_gpu: f.gpu,
                    uploaded_bytes,
                    variant: f.variant,
                    variant_name: f.variant_name,
                    tiles: f.tiles,
                });
            }
        }
    }
}

/// Where a band of step `2·dt` begins, for the wanted start `start` and the finer band's
/// step `dt`: half a fine step past an even multiple of `dt` (at or below `start`). The
/// finer band's last sample is then that even multiple and the coarser band's first the
/// next one, a coarse step later, which is what its tables are corrected for: a
/// pre-integrated segment across the boundary had been composited as a coarse step over a
/// fine step's length wherever the wanted start fell after an odd multiple (one step's worth
/// of extra opacity on a shell at that distance). Half a step clear of both lattice points,
/// the boundary is not moved by rounding.
fn band_start(start: f32, dt: f32) -> f32 {
    let pair = 2.0 * dt as f64;
    let j = (start as f64 / pair).floor().max(0.0);
    (j * pair + 0.5 * dt as f64) as f32
}

/// This machine's physical memory in MiB (`None` where the system will not say).
fn physical_memory_mb() -> Option<u64> {
    // SAFETY: `sysconf` only reads system parameters.
    let (pages, size) = unsafe {
        (
            libc::sysconf(libc::_SC_PHYS_PAGES),
            libc::sysconf(libc::_SC_PAGESIZE),
        )
    };
    (pages > 0 && size > 0).then(|| (pages as u64).saturating_mul(size as u64) >> 20)
}

fn validate(s: &RenderSettings) -> Result<()> {
    s.check().map_err(|(_, message)| anyhow::anyhow!(message))
}

/// A CPU atlas (`render.{key}` MiB) is allocated whole at start: past the machine's
/// memory the allocation would abort the process instead of failing here. (A GPU atlas
/// lives in the adapter's memory, which its own limit bounds.)
fn cpu_atlas_fits(key: &str, mb: u64) -> Result<()> {
    if let Some(mem) = physical_memory_mb() {
        if mb > mem {
            bail!("render.{key} = {mb} exceeds this machine's memory ({mem} MiB)");
        }
    }
    Ok(())
}

/// Pixels that can see `region`: the bounding box of its projected corners, or the whole
/// image when the eye is inside or behind a corner. For a wall the box is found on the
/// frustum's plane and then cut to the tiles (mullion pixels are not in the image).
fn screen_rect(view: &View, region: &Region) -> Rect {
    let full = Rect {
        x: 0,
        y: 0,
        w: view.width,
        h: view.height,
    };
    if (0..3).any(|a| !(region.lo[a] < region.hi[a])) {
        return Rect::EMPTY;
    }
    let f = view.forward;
    let du2: f32 = view.du.iter().map(|v| v * v).sum();
    let dv2: f32 = view.dv.iter().map(|v| v * v).sum();
    let (pw, ph) = view.plane;
    let (mut x0, mut y0, mut x1, mut y1) = (f32::MAX, f32::MAX, f32::MIN, f32::MIN);
    for c in 0..8 {
        let w = [0, 1, 2].map(|k| {
            if c >> k & 1 == 0 {
                region.lo[k]
            } else {
                region.hi[k]
            }
        });
        let p = view.relative(w);
        let z = p[0] * f[0] + p[1] * f[1] + p[2] * f[2];
        let len = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        if z <= 1e-4 * len.max(1e-30) {
            return full;
        }
        let px = (p[0] * view.du[0] + p[1] * view.du[1] + p[2] * view.du[2]) / (du2 * z);
        let py = (p[0] * view.dv[0] + p[1] * view.dv[1] + p[2] * view.dv[2]) / (dv2 * z);
        let x = pw as f32 / 2.0 + px;
        let y = ph as f32 / 2.0 + py;
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if !(x0.is_finite() && x1.is_finite() && y0.is_finite() && y1.is_finite()) {
        return full;
    }
    let xa = (x0.floor() - 1.0).max(0.0) as u32;
    let ya = (y0.floor() - 1.0).max(0.0) as u32;
    let xb = ((x1.ceil() + 1.0).max(0.0) as u32).min(pw);
    let yb = ((y1.ceil() + 1.0).max(0.0) as u32).min(ph);
    if xa >= xb || ya >= yb {
        return Rect::EMPTY;
    }
    plane_rect_to_image(view, xa, ya, xb, yb)
}

/// The image pixels whose plane pixels lie in `[xa, xb) × [ya, yb)`: the rectangle itself
/// for a plain image, the bounding box of its parts in the tiles for a wall.
fn plane_rect_to_image(view: &View, xa: u32, ya: u32, xb: u32, yb: u32) -> Rect {
    let m = view.tiles;
    if m.is_plain() {
        return Rect {
            x: xa,
            y: ya,
            w: xb - xa,
            h: yb - ya,
        };
    }
    let (tw, th) = (view.width, m.tile_h);
    let tiles = view.height / th;
    let (mut ix0, mut iy0, mut ix1, mut iy1) = (u32::MAX, u32::MAX, 0, 0);
    for t in 0..tiles {
        let (c, r) = (t % m.cols, t / m.cols);
        let (ox, oy) = (c * m.pitch_x, r * m.pitch_y);
        let (cx0, cx1) = (xa.max(ox), xb.min(ox + tw));
        let (cy0, cy1) = (ya.max(oy), yb.min(oy + th));
        if cx0 < cx1 && cy0 < cy1 {
            ix0 = ix0.min(cx0 - ox);
            ix1 = ix1.max(cx1 - ox);
            iy0 = iy0.min(t * th + cy0 - oy);
            iy1 = iy1.max(t * th + cy1 - oy);
        }
    }
    Rect::spanning(ix0, iy0, ix1, iy1)
}

/// Puts back into `f` the tiles of `prev` (the round before, same view and region) that
/// `cast` does not mark, with their feedback and counters, so that `f`'s image, feedback
/// and counters describe the whole frame again.
fn keep_tiles(f: &mut Frame, mut prev: Frame, cast: &[bool]) -> Result<()> {
    use crate::raycast::TILE;
    let r = f.image.rect;
    anyhow::ensure!(
        prev.image.rect == r && prev.tiles.len() == f.tiles.len() && cast.len() == f.tiles.len(),
        "internal: a feedback round changed the frame's tiles"
    );
    let tiles_x = r.w.div_ceil(TILE) as usize;
    let w = r.w as usize;
    for (ti, _) in cast.iter().enumerate().filter(|(_, &c)| !c) {
        let (x0, y0) = (
            (ti % tiles_x) * TILE as usize,
            (ti / tiles_x) * TILE as usize,
        );
        let tw = (TILE as usize).min(w - x0);
        let th = (TILE as usize).min(r.h as usize - y0);
        for y in y0..y0 + th {
            let row = y * w + x0..y * w + x0 + tw;
            f.image.pixels[row.clone()].copy_from_slice(&prev.image.pixels[row]);
        }
        f.tiles[ti] = std::mem::take(&mut prev.tiles[ti]);
    }
    f.stats = CastStats::default();
    for t in &f.tiles {
        f.stats += t.stats;
    }
    f.feedback = feedback_of(&f.tiles);
    Ok(())
}

/// The requests of a frame's tiles, merged.
fn feedback_of(tiles: &[crate::raycast::TileOut]) -> Feedback {
    let mut feedback = Feedback::default();
    for t in tiles {
        feedback.add(&t.feedback);
    }
    feedback
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::first_k;

    /// Across every band boundary the finer band's last sample and the coarser band's
    /// first lie one coarse step apart, as the coarser band's tables assume, in the casters'
    /// own f32 lattice arithmetic, and the boundary moves by at most two fine steps.
    #[test]
    fn a_band_begins_one_coarse_step_after_the_finer_bands_last_sample() {
        let mut rng = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut odd_before = 0;
        for _ in 0..20_000 {
            let dt = (0.01 + 3.0 * next()) as f32;
            let start = (dt as f64 * (0.3 + 5000.0 * next())) as f32;
            let s = band_start(start, dt);
            assert!(
                s > 0.0 && (s - start).abs() <= 2.0 * dt,
                "{start} → {s} (dt {dt})"
            );
            // The finer band's samples are k·dt < s; the coarser band's k'·2dt ≥ s.
            let last = (first_k(s, dt) - 1) as f32 * dt;
            let first = first_k(s, 2.0 * dt) as f32 * (2.0 * dt);
            let gap = first - last;
            assert!(
                (gap - 2.0 * dt).abs() <= 1e-3 * dt.max(first.abs() * 1e-6),
                "start {start} → {s}, dt {dt}: last fine sample {last}, first coarse {first}"
            );
            // Without the snap, half the starts had left a single fine step.
            let raw_last = (first_k(start, dt) - 1) as f32 * dt;
            let raw_first = first_k(start, 2.0 * dt) as f32 * (2.0 * dt);
            if (raw_first - raw_last) < 1.5 * dt {
                odd_before += 1;
            }
        }
        assert!(odd_before > 5_000, "{odd_before}");
    }
}
