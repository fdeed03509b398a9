//! The wgpu backend of the engine: the atlas pools (volume bricks in their own sample width,
//! in a storage buffer or a filterable 3D texture; horizon tiles), the page tables and the
//! transfer-function tables live on the GPU, a WGSL compute shader ([`SHADER`]) casts the rays with the CPU
//! caster's semantics, and the feedback is counted and compacted on the GPU.
//!
//! The engine keeps the bookkeeping (which page is in which slot, the page tables) on the
//! host, exactly as for the CPU backend, and hands this module:
//!
//! * newly resident pages ([`GpuCaster::write_page`]), encoded in the pool's format and
//!   written into their slot;
//! * the page tables ([`GpuCaster::sync_table`]): only the runs of entries that changed
//!   since the last frame are written;
//! * newly resident horizon tiles ([`GpuCaster::write_horizon_page`]) into the horizon pool;
//! * per frame, the [`FrameParams`], [`VolumeParams`] (with the volume's slices) and
//!   [`HorizonParams`] of `strata_common::gpu`, and the horizons' tile bounds.
//!
//! [`GpuCaster::cast`] returns the region's pixels, the compacted feedback
//! (`(global page-table entry, rays)` pairs, no per-pixel buffer crosses the bus) and the
//! counters, with the bytes read back.

use std::collections::HashMap;
use std::sync::{mpsc, Arc, Mutex};
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use strata_common::effects::EffectSet;
use strata_common::gpu::{
    FrameParams, HorizonParams, VolumeParams, FRAME_SHADING, HORIZON_LIGHTING, MAX_HORIZONS,
    VOLUME_PREINTEGRATED,
};

pub mod backend;

/// The WGSL of the caster and the feedback compaction.
pub const SHADER: &str = include_str!("cast.wgsl");
/// Volumes the GPU caster mixes at most.
pub const MAX_VOLUMES: usize = 4;
const WORKGROUP: u32 = 8;
const COMPACT_WORKGROUP: u32 = 64;

/// Which adapter to take.
#[derive(Clone, Debug, Default)]
pub struct AdapterChoice {
    /// An index into the adapter list, or a case-insensitive substring of the adapter's name.
    pub adapter: Option<String>,
    /// Accept software adapters (lavapipe, llvmpipe).
    pub allow_software: bool,
    /// With no explicit adapter, take the `spread % n`-th of the `n` best adapters of the same
    /// kind, so that local workers on a multi-GPU node each take their own GPU (the local
    /// spawner passes the worker's index in [`GPU_SLOT_ENV`]).
    pub spread: Option<usize>,
}

/// The environment variable through which local spawning gives each worker its index.
pub const GPU_SLOT_ENV: &str = "STRATA_GPU_SLOT";

/// What one GPU frame produced.
pub struct GpuCast {
    /// Pixels of the frame's rectangle, rows top to bottom.
    pub pixels: Vec<[f32; 4]>,
    /// `(global page-table entry, rays that entered it)`, unordered; a region cast in bands
    /// lists an entry once per band that asked for it (the counts add up).
    pub feedback: Vec<(u32, u32)>,
    /// Trilinear samples taken.
    pub samples: u64,
    /// Lattice samples skipped as empty space.
    pub skipped: u64,
    /// Rays ended by early termination.
    pub terminated: u64,
    /// Rays cast.
    pub rays: u64,
    /// Horizon crossings composited.
    pub hits: u64,
    /// Bytes read back: pixels, feedback length and list, counters.
    pub readback_bytes: u64,
    /// Feedback bytes read back (length and list).
    pub feedback_bytes: u64,
}

/// A storage buffer that grows when a larger content arrives.
struct Grow {
    label: &'static str,
    usage: wgpu::BufferUsages,
    buf: Option<wgpu::Buffer>,
    /// Bytes of `buf` when it was made without error; 0 after a failed allocation, whose
    /// buffer (invalid, but reporting the size asked for) is then made again next time
    /// instead of being taken as large enough for good.
    size: u64,
    /// Why the last allocation was refused.
    refused: Option<String>,
    /// Whether the buffer is made again, smaller, when a window of calls needed much less
    /// (the image and readback buffers, sized by the frame; not the pools and tables, which
    /// other calls only make sure exist). See [`ShrinkWindow`].
    shrink: Option<ShrinkWindow>,
}

/// Calls in a window of the buffer's use (see [`ShrinkWindow`]). A frame calls once per
/// leaf, band and feedback round (the readback buffer twice), so a window spans several
/// frames of a worker with a few leaves.
pub const SHRINK_WINDOW: u32 = 128;

/// Buffers under this many bytes are never shrunk (not worth an allocation).
const SHRINK_FLOOR: u64 = 16 << 20;

/// When a buffer sized by each call is made again, smaller: after a window of
/// [`SHRINK_WINDOW`] calls since it was made (or last looked at) whose largest need is at
/// most a quarter of it, at that largest need. One large frame (a powerwall's, a study's
/// 8K) then stops holding its memory on a GPU that other workers share, while sizes that
/// alternate within a window (a worker's large and small leaves, occlusion's first pass at
/// a fraction of the frame) keep the buffer at the largest of them and never reallocate.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct ShrinkWindow {
    calls: u32,
    largest: u64,
}

impl ShrinkWindow {
    /// Records a call needing `bytes` of a buffer of `size`: the smaller size to make it
    /// at, when this call closes a window that needed at most a quarter of it.
    fn observe(&mut self, size: u64, bytes: u64) -> Option<u64> {
        self.calls += 1;
        self.largest = self.largest.max(bytes);
        if self.calls < SHRINK_WINDOW {
            return None;
        }
        let largest = self.largest;
        *self = ShrinkWindow::default();
        (size > SHRINK_FLOOR && largest <= size / 4).then_some(largest)
    }
}

impl Grow {
    fn new(label: &'static str, usage: wgpu::BufferUsages) -> Self {
        Grow {
            label,
            usage,
            buf: None,
            size: 0,
            refused: None,
            shrink: None,
        }
    }

    /// A buffer sized by each call, made again smaller when a window of calls needed much
    /// less (see [`ShrinkWindow`]).
    fn shrinking(label: &'static str, usage: wgpu::BufferUsages) -> Self {
        Grow {
            shrink: Some(ShrinkWindow::default()),
            ..Grow::new(label, usage)
        }
    }

    /// Makes room for `bytes`; true if the buffer was (re)created. An allocation the device
    /// refuses (out of memory, past its largest buffer) is logged, and the frame that binds
    /// the invalid buffer fails; the next call allocates again.
    fn ensure(&mut self, device: &wgpu::Device, bytes: u64) -> bool {
        let bytes = bytes.max(16).next_multiple_of(16);
        if self.buf.is_some() && self.size >= bytes {
            let Some(smaller) = self
                .shrink
                .as_mut()
                .and_then(|w| w.observe(self.size, bytes))
            else {
                return false;
            };
            // Made before the large one is freed: a refusal keeps the buffer that works.
            let mut made = None;
            let ok = checked(device, self.label, || {
                made = Some(device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(self.label),
                    size: smaller,
                    usage: self.usage,
                    mapped_at_creation: false,
                }));
            });
            return match ok {
                Ok(()) => {
                    tracing::debug!(
                        buffer = self.label,
                        from = self.size,
                        to = smaller,
                        "shrank a GPU buffer"
                    );
                    self.buf = made;
                    self.size = smaller;
                    true
                }
                Err(e) => {
                    tracing::warn!(
                        buffer = self.label,
                        smaller,
                        "GPU allocation refused, keeping the larger buffer: {e:#}"
                    );
                    false
                }
            };
        }
        if let Some(w) = &mut self.shrink {
            *w = ShrinkWindow::default();
        }
        self.buf = None; // free before allocating the new one
        let mut made = None;
        let ok = checked(device, self.label, || {
            made = Some(device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(self.label),
                size: bytes,
                usage: self.usage,
                mapped_at_creation: false,
            }));
        });
        self.size = match &ok {
            Ok(()) => bytes,
            Err(e) => {
                tracing::warn!(buffer = self.label, bytes, "GPU allocation refused: {e:#}");
                0
            }
        };
        self.refused = ok.err().map(|e| format!("{e:#}"));
        self.buf = made;
        true
    }

    /// Fails with the device's message if the last allocation was refused.
    fn check(&self, what: &str) -> Result<()> {
        match &self.refused {
            Some(e) => bail!("{what}: {e}"),
            None => Ok(()),
        }
    }

    fn get(&self) -> &wgpu::Buffer {
        self.buf.as_ref().expect("ensured before use")
    }
}

/// The volume pool as a 3D texture, for the texture unit's filter: slots are `page³` blocks
/// on a `grid` of pages.
struct TexturePool {
    texture: wgpu::Texture,
    view: wgpu::TextureView,
    grid: [u32; 3],
    page: u32,
    texel_bytes: u32,
}

/// The GPU caster: device, pipelines and the buffers kept between frames.
pub struct GpuCaster {
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    limits: wgpu::Limits,
    module: wgpu::ShaderModule,
    /// Cast pipelines by the effects compiled in (shading, several volumes, horizons,
    /// lighting, slices: [`pipeline_effects`]), pool width and filter (texture unit or
    /// shader).
    pipelines: HashMap<(EffectSet, u32, bool), wgpu::ComputePipeline>,
    compact: wgpu::ComputePipeline,
    frame: wgpu::Buffer,
    vols: wgpu::Buffer,
    hors: wgpu::Buffer,
    hbounds: Grow,
    /// Cross-worker occlusion: per-block ray thresholds (binding 17).
    occl: Grow,
    hpool: Grow,
    levels: Grow,
    table: Grow,
    transparent: Grow,
    tf: Grow,
    pool: Grow,
    feedback: Grow,
    fb_list: Grow,
    fb_len: wgpu::Buffer,
    stats: wgpu::Buffer,
    out: Grow,
    read: Grow,
    table_mirror: Vec<u32>,
    transparent_mirror: Vec<u32>,
    tf_mirror: Vec<[f32; 4]>,
    /// The generation and length of the pre-integration tables at the start of the
    /// transfer-function buffer (see [`GpuCaster::sync_frame_tables`]).
    tf_pre: Option<(u64, usize)>,
    levels_mirror: Vec<[u32; 4]>,
    hbounds_mirror: Vec<[f32; 2]>,
    page_bytes: u64,
    pool_bits: u32,
    hpage_bytes: u64,
    /// The texture pool (`render.gpu_filter = "hardware"`), else a 1-texel stand-in is bound.
    tex: Option<TexturePool>,
    dummy_tex: wgpu::TextureView,
    sampler: wgpu::Sampler,
    /// Bytes written to the device since the last [`take_uploaded`](Self::take_uploaded).
    uploaded: u64,
    uncaptured: Arc<Mutex<Option<String>>>,
    /// A cap on a band's pixels below the adapter's binding ([`GpuCaster::set_band_pixels`]).
    band_cap: Option<u64>,
    /// Regions cast in more than one band.
    bands_cast: u64,
}

/// The effects a cast pipeline is specialised on: those `cast.wgsl` has override constants
/// for (it has no separate single-volume code).
pub fn pipeline_effects(compiled: EffectSet) -> EffectSet {
    let on = EffectSet::VOLUMES
        .union(EffectSet::HORIZONS)
        .union(EffectSet::LIGHTING)
        .union(EffectSet::SLICES)
        .union(EffectSet::SHADING)
        .union(EffectSet::PREINTEGRATED);
    EffectSet::from_bits(compiled.bits() & on.bits())
}

const STORAGE_DST: wgpu::BufferUsages =
    wgpu::BufferUsages::STORAGE.union(wgpu::BufferUsages::COPY_DST);
const STORAGE_SRC_DST: wgpu::BufferUsages = STORAGE_DST.union(wgpu::BufferUsages::COPY_SRC);

/// The process's one wgpu instance: Vulkan unless `WGPU_BACKEND` names others (`gl`,
/// `vulkan,gl`).
///
/// One instance serves every engine of the process, rather than a Vulkan instance created
/// and destroyed per engine, several at once on test threads: with one per engine the GPU
/// test binary segfaulted on an H200 (twice, 2 test threads and `RUST_LOG=info`, a debug
/// build; not with 8 threads and no `RUST_LOG`; the fault inside the driver was not
/// pinned down). wgpu's debug flags (debug-utils messenger, validation) are opt-in through
/// `WGPU_DEBUG` / `WGPU_VALIDATION` instead of following the build's debug assertions, so
/// test builds drive the GPU as release builds do.
fn instance() -> (wgpu::Instance, wgpu::Backends) {
    static INSTANCE: std::sync::OnceLock<(wgpu::Instance, wgpu::Backends)> =
        std::sync::OnceLock::new();
    INSTANCE
        .get_or_init(|| {
            let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
            desc.flags = wgpu::InstanceFlags::empty().with_env();
            if std::env::var_os("WGPU_BACKEND").is_none() {
                desc.backends = wgpu::Backends::VULKAN;
            }
            let backends = desc.backends;
            (wgpu::Instance::new(desc), backends)
        })
        .clone()
}

/// The adapters wgpu sees, as `(index, name, backend, software)`.
pub fn list_adapters() -> Vec<(usize, String, String, bool)> {
    let (instance, backends) = instance();
    let adapters = pollster::block_on(instance.enumerate_adapters(backends));
    adapters
        .iter()
        .enumerate()
        .map(|(i, a)| {
            let info = a.get_info();
            (
                i,
                info.name.clone(),
                format!("{:?}", info.backend),
                info.device_type == wgpu::DeviceType::Cpu,
            )
        })
        .collect()
}

fn pick_adapter(choice: &AdapterChoice) -> Result<wgpu::Adapter> {
    let (instance, backends) = instance();
    let mut adapters = pollster::block_on(instance.enumerate_adapters(backends));
    let usable = |a: &wgpu::Adapter| {
        a.get_downlevel_capabilities()
            .flags
            .contains(wgpu::DownlevelFlags::COMPUTE_SHADERS)
    };
    let software = |a: &wgpu::Adapter| a.get_info().device_type == wgpu::DeviceType::Cpu;
    let names = || adapters_desc(&pollster::block_on(instance.enumerate_adapters(backends)));
    if let Some(want) = &choice.adapter {
        // A blank selector is a substring of every name: it would pick the first adapter.
        if want.trim().is_empty() {
            bail!(
                "render.gpu_adapter is empty: name an adapter (part of its name) or give its index ({})",
                names()
            );
        }
        let found = match want.trim().parse::<usize>() {
            Ok(i) if i < adapters.len() => Some(adapters.swap_remove(i)),
            Ok(i) => bail!(
                "render.gpu_adapter = {i}: there are only {} adapters ({})",
                adapters.len(),
                names()
            ),
            Err(_) => {
                let w = want.to_lowercase();
                let pos = adapters
                    .iter()
                    .position(|a| a.get_info().name.to_lowercase().contains(&w));
                pos.map(|i| adapters.swap_remove(i))
            }
        };
        let a = found.ok_or_else(|| {
            anyhow!(
                "render.gpu_adapter = {want:?} matches no adapter ({})",
                names()
            )
        })?;
        if !usable(&a) {
            bail!("adapter {} has no compute shaders", a.get_info().name);
        }
        if software(&a) && !choice.allow_software {
            bail!(
                "adapter {} is a software renderer (render.backend = \"gpu\" accepts it)",
                a.get_info().name
            );
        }
        return Ok(a);
    }
    // Prefer discrete, then integrated, then anything else; software only when allowed.
    let rank = |a: &wgpu::Adapter| match a.get_info().device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu | wgpu::DeviceType::Other => 2,
        wgpu::DeviceType::Cpu => 3,
    };
    adapters.retain(|a| usable(a) && (choice.allow_software || !software(a)));
    adapters.sort_by_key(|a| (rank(a), a.get_info().backend != wgpu::Backend::Vulkan));
    if let (Some(i), Some(best)) = (choice.spread, adapters.first()) {
        let key = |a: &wgpu::Adapter| (rank(a), a.get_info().backend);
        let k = key(best);
        let n = adapters.iter().take_while(|a| key(a) == k).count();
        if n > 1 {
            return Ok(adapters.swap_remove(i % n));
        }
    }
    adapters.into_iter().next().ok_or_else(|| {
        anyhow!(
            "no {}GPU adapter with compute shaders (adapters: {}; without a GPU, \
             `apt-get install mesa-vulkan-drivers libvulkan1` provides lavapipe)",
            if choice.allow_software {
                ""
            } else {
                "hardware "
            },
            names()
        )
    })
}

fn adapters_desc(a: &[wgpu::Adapter]) -> String {
    if a.is_empty() {
        return "none".into();
    }
    a.iter()
        .enumerate()
        .map(|(i, a)| {
            let info = a.get_info();
            format!(
                "{i}: {} ({:?}, {:?})",
                info.name, info.backend, info.device_type
            )
        })
        .collect::<Vec<_>>()
        .join("; ")
}

impl GpuCaster {
    /// Opens an adapter and builds the pipelines. Fails, never panics, when there is no
    /// suitable adapter.
    pub fn new(choice: &AdapterChoice) -> Result<Self> {
        let adapter = pick_adapter(choice)?;
        let info = adapter.get_info();
        if info.device_type == wgpu::DeviceType::Cpu && info.name.contains("llvmpipe") {
            // Mesa's gallivm stops every loop nest after 65 535 back-edges per invocation
            // (LP_MAX_TGSI_LOOP_ITERATIONS), so a ray is cut short after about 16 000
            // samples (hard cases 15 and 16); a hardware GPU has no such limit.
            tracing::warn!(
                adapter = %info.name,
                "software Vulkan: rays of more than about 16 000 samples are cut short (llvmpipe's loop limit)"
            );
        }
        // The adapter's own limits: the WebGPU defaults cap a storage binding at 128 MiB.
        let limits = adapter.limits();
        if limits.max_storage_buffers_per_shader_stage < 13 {
            bail!(
                "adapter {} binds {} storage buffers per stage; the caster needs 13",
                info.name,
                limits.max_storage_buffers_per_shader_stage
            );
        }
        // Filterable 16-bit normalized and f32 textures, where the adapter has them (the
        // hardware filter of 16-bit and f32 pools needs them).
        let features = adapter.features()
            & (wgpu::Features::TEXTURE_FORMAT_16BIT_NORM | wgpu::Features::FLOAT32_FILTERABLE);
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("strata-gpu-caster"),
            required_features: features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .with_context(|| format!("opening {} ({:?})", info.name, info.backend))?;
        let uncaptured = Arc::new(Mutex::new(None));
        let sink = uncaptured.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            let mut slot = sink.lock().unwrap_or_else(|p| p.into_inner());
            slot.get_or_insert_with(|| e.to_string());
        }));
        let (module, compact) = checked(&device, "building the caster's shader", || {
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("cast.wgsl"),
                source: wgpu::ShaderSource::Wgsl(SHADER.into()),
            });
            let compact = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("feedback compaction"),
                layout: None,
                module: &module,
                entry_point: Some("compact"),
                compilation_options: Default::default(),
                cache: None,
            });
            (module, compact)
        })?;
        let uniform = |label, size| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let frame = uniform("frame", std::mem::size_of::<FrameParams>() as u64);
        let vols = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("volumes"),
            size: (MAX_VOLUMES * std::mem::size_of::<VolumeParams>()) as u64,
            usage: STORAGE_DST,
            mapped_at_creation: false,
        });
        let hors = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("horizons"),
            size: (MAX_HORIZONS * std::mem::size_of::<HorizonParams>()) as u64,
            usage: STORAGE_DST,
            mapped_at_creation: false,
        });
        let small = |label| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: 32,
                usage: STORAGE_SRC_DST,
                mapped_at_creation: false,
            })
        };
        let fb_len = small("feedback length");
        let stats = small("counters");
        let dummy_tex = device
            .create_texture(&wgpu::TextureDescriptor {
                label: Some("no texture pool"),
                size: wgpu::Extent3d {
                    width: 1,
                    height: 1,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D3,
                format: wgpu::TextureFormat::R8Unorm,
                usage: wgpu::TextureUsages::TEXTURE_BINDING,
                view_formats: &[],
            })
            .create_view(&Default::default());
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("pool filter"),
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            ..Default::default()
        });
        Ok(GpuCaster {
            device,
            queue,
            info,
            limits,
            module,
            pipelines: HashMap::new(),
            compact,
            frame,
            vols,
            hors,
            hbounds: Grow::new("horizon tile bounds", STORAGE_DST),
            occl: Grow::new("occlusion ray thresholds", STORAGE_DST),
            hpool: Grow::new("horizon pool", STORAGE_DST),
            levels: Grow::new("levels", STORAGE_DST),
            table: Grow::new("page table", STORAGE_DST),
            transparent: Grow::new("transparent pages", STORAGE_DST),
            tf: Grow::new("transfer functions", STORAGE_DST),
            pool: Grow::new("atlas pool", STORAGE_DST),
            feedback: Grow::new("feedback counters", STORAGE_DST),
            fb_list: Grow::new("feedback list", STORAGE_SRC_DST),
            fb_len,
            stats,
            out: Grow::shrinking("image", STORAGE_SRC_DST),
            read: Grow::shrinking(
                "readback",
                wgpu::BufferUsages::MAP_READ.union(wgpu::BufferUsages::COPY_DST),
            ),
            table_mirror: Vec::new(),
            transparent_mirror: Vec::new(),
            tf_mirror: Vec::new(),
            tf_pre: None,
            levels_mirror: Vec::new(),
            hbounds_mirror: Vec::new(),
            page_bytes: 0,
            pool_bits: 32,
            hpage_bytes: 0,
            tex: None,
            dummy_tex,
            sampler,
            uploaded: 0,
            uncaptured,
            band_cap: None,
            bands_cast: 0,
        })
    }

    /// The adapter, e.g. `NVIDIA H100 80GB HBM3 (Vulkan)` or `llvmpipe (LLVM 15.0.6, 256 bits) (Vulkan)`.
    pub fn adapter_name(&self) -> String {
        format!("{} ({:?})", self.info.name, self.info.backend)
    }

    /// Whether the adapter is a CPU implementation (lavapipe, llvmpipe).
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// The most pixels one band of a cast may have: its RGBA f32 output is one storage
    /// binding. Larger regions are cast in bands.
    pub fn max_frame_pixels(&self) -> u64 {
        let bind = self
            .limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
            / 16;
        self.band_cap.map_or(bind, |c| c.min(bind)).max(1)
    }

    /// The largest storage binding the adapter allows, in bytes.
    pub fn max_binding_bytes(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
    }

    /// Pool slots of `slot_bytes` the adapter can bind in one buffer, and whose elements
    /// the shader can index: it addresses them in u32 (an 8-bit element per byte), and an
    /// adapter may bind more than 4 GiB (Metal reports its buffer size).
    pub fn max_slots(&self, slot_bytes: u64) -> usize {
        let bind = self
            .limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
            .min(u32::MAX as u64);
        (bind / slot_bytes.max(1)) as usize
    }

    /// Allocates the volume pool: `slots` slots of `slot_bytes`, elements of `bits` bits
    /// (`strata_common::gpu::PoolFormat`).
    pub fn alloc_pool(&mut self, slots: usize, slot_bytes: u64, bits: u32) -> Result<()> {
        if !matches!(bits, 8 | 16 | 32) || !slot_bytes.is_multiple_of(4) {
            bail!("GPU pool: {bits}-bit elements in slots of {slot_bytes} bytes");
        }
        let bytes = slots as u64 * slot_bytes;
        self.page_bytes = slot_bytes;
        self.pool_bits = bits;
        self.pool.ensure(&self.device, bytes);
        self.pool.check("allocating the atlas pool")
    }

    /// Writes a page, encoded in the pool's format, into its slot.
    pub fn write_page(&mut self, slot: u32, bytes: &[u8]) {
        if let Some(t) = &self.tex {
            let [gx, gy, _] = t.grid;
            let p = t.page;
            // A slot's bytes may be padded to whole words; the texture takes p³ texels.
            let bytes = &bytes[..(p as usize).pow(3) * t.texel_bytes as usize];
            self.queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &t.texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d {
                        x: slot % gx * p,
                        y: slot / gx % gy * p,
                        z: slot / (gx * gy) * p,
                    },
                    aspect: wgpu::TextureAspect::All,
                },
                bytes,
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(p * t.texel_bytes),
                    rows_per_image: Some(p),
                },
                wgpu::Extent3d {
                    width: p,
                    height: p,
                    depth_or_array_layers: p,
                },
            );
            self.uploaded += bytes.len() as u64;
            return;
        }
        debug_assert_eq!(bytes.len() as u64, self.page_bytes);
        self.queue
            .write_buffer(self.pool.get(), slot as u64 * self.page_bytes, bytes);
        self.uploaded += bytes.len() as u64;
    }

    /// Whether the adapter can filter a texture pool of `bits`-bit elements.
    pub fn can_filter(&self, bits: u32) -> bool {
        let f = self.device.features();
        match bits {
            8 => true,
            16 => f.contains(wgpu::Features::TEXTURE_FORMAT_16BIT_NORM),
            _ => f.contains(wgpu::Features::FLOAT32_FILTERABLE),
        }
    }

    /// Slots of `page`³ texels of `texel_bytes` a 3D texture pool can hold on this adapter:
    /// within its largest 3D texture, and (as for buffers) its largest allocation.
    pub fn max_texture_slots(&self, page: u32, texel_bytes: u32) -> usize {
        let per = (self.limits.max_texture_dimension_3d / page.max(1)) as usize;
        let bytes = (page as u64).pow(3) * texel_bytes as u64;
        (per * per * per).min((self.limits.max_buffer_size / bytes.max(1)) as usize)
    }

    /// Allocates the volume pool as a 3D texture of `slots` pages of `page`³ texels of `bits`
    /// bits (unsigned normalized for 8 and 16 bits, f32 for 32), for the texture unit's filter.
    pub fn alloc_texture_pool(&mut self, slots: usize, page: u32, bits: u32) -> Result<()> {
        let format = match bits {
            8 => wgpu::TextureFormat::R8Unorm,
            16 => wgpu::TextureFormat::R16Unorm,
            32 => wgpu::TextureFormat::R32Float,
            _ => bail!("texture pool: {bits}-bit texels"),
        };
        if !self.can_filter(bits) {
            bail!(
                "adapter {} cannot filter {format:?} textures; use render.gpu_filter = \"exact\"",
                self.info.name
            );
        }
        let per = self.limits.max_texture_dimension_3d / page.max(1);
        let slots = slots.max(1) as u32;
        let gx = slots.min(per);
        let gy = slots.div_ceil(gx).min(per);
        let gz = slots.div_ceil(gx * gy);
        if gz > per {
            bail!("{slots} texture-pool slots of {page}³ exceed the adapter's 3D texture size");
        }
        let device = &self.device;
        let texture = checked(device, "allocating the texture pool", || {
            device.create_texture(&wgpu::TextureDescriptor {
                label: Some("atlas texture pool"),
                size: wgpu::Extent3d {
                    width: gx * page,
                    height: gy * page,
                    depth_or_array_layers: gz * page,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D3,
                format,
                usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
                view_formats: &[],
            })
        })?;
        let view = texture.create_view(&Default::default());
        self.pool_bits = bits;
        self.tex = Some(TexturePool {
            texture,
            view,
            grid: [gx, gy, gz],
            page,
            texel_bytes: bits / 8,
        });
        Ok(())
    }

    /// Allocates the horizon pool: `slots` tiles of `page_samples` f32 heights.
    pub fn alloc_horizon_pool(&mut self, slots: usize, page_samples: usize) -> Result<()> {
        let bytes = slots as u64 * page_samples as u64 * 4;
        self.hpage_bytes = page_samples as u64 * 4;
        self.hpool.ensure(&self.device, bytes);
        self.hpool.check("allocating the horizon pool")
    }

    /// Test hook (after a first cast): a write past the end of the readback buffer, a real
    /// validation error that wgpu reports to the uncaptured-error handler (as it would an
    /// earlier write's failure), so tests can check that the caster recovers from one.
    #[doc(hidden)]
    pub fn write_past_a_buffer(&mut self) {
        let b = self.read.get();
        self.queue.write_buffer(b, b.size(), &[0u8; 4]);
    }

    /// Bytes of the image buffer (0 before a frame).
    #[doc(hidden)]
    pub fn image_buffer_bytes(&self) -> u64 {
        self.out.size
    }

    /// Test hook: asks for an image buffer past the device's largest buffer (an allocation
    /// it refuses, as it would one past free memory). Returns whether it was refused.
    #[doc(hidden)]
    pub fn fail_an_allocation(&mut self) -> bool {
        let too_big = self.device.limits().max_buffer_size.saturating_add(16);
        self.out.ensure(&self.device, too_big);
        self.out.size == 0
    }

    /// Writes a horizon tile into its slot of the horizon pool.
    pub fn write_horizon_page(&mut self, slot: u32, heights: &[f32]) {
        let bytes: &[u8] = bytemuck::cast_slice(heights);
        debug_assert_eq!(bytes.len() as u64, self.hpage_bytes);
        self.queue
            .write_buffer(self.hpool.get(), slot as u64 * self.hpage_bytes, bytes);
        self.uploaded += bytes.len() as u64;
    }

    /// Brings the device's global page table up to `entries`, writing only the runs that
    /// changed (runs closer than 64 entries are merged into one write). Returns the entries
    /// written.
    pub fn sync_table(&mut self, entries: &[u32]) -> usize {
        let fresh = self.table.ensure(&self.device, entries.len() as u64 * 4);
        // Feedback counters cover the same entries.
        if self.feedback.ensure(&self.device, entries.len() as u64 * 4) {
            let zero = vec![0u8; self.feedback.get().size() as usize];
            self.queue.write_buffer(self.feedback.get(), 0, &zero);
        }
        self.fb_list.ensure(&self.device, entries.len() as u64 * 8);
        if fresh || self.table_mirror.len() != entries.len() {
            self.queue
                .write_buffer(self.table.get(), 0, bytemuck::cast_slice(entries));
            self.table_mirror = entries.to_vec();
            self.uploaded += entries.len() as u64 * 4;
            return entries.len();
        }
        let mut written = 0;
        let mut i = 0;
        let n = entries.len();
        while i < n {
            if entries[i] == self.table_mirror[i] {
                i += 1;
                continue;
            }
            let start = i;
            let mut end = i + 1; // exclusive end of the last changed entry
            let mut j = i + 1;
            while j < n && j < end + 64 {
                if entries[j] != self.table_mirror[j] {
                    end = j + 1;
                }
                j += 1;
            }
            self.queue.write_buffer(
                self.table.get(),
                start as u64 * 4,
                bytemuck::cast_slice(&entries[start..end]),
            );
            self.table_mirror[start..end].copy_from_slice(&entries[start..end]);
            written += end - start;
            i = end;
        }
        self.uploaded += written as u64 * 4;
        written
    }

    /// Brings the per-entry transparency bits, the level records, the transfer-function and
    /// colour-map tables and the horizons' tile bounds up to date (each written only when it
    /// changed).
    ///
    /// The transfer-function buffer holds `pre.1` (the pre-integration tables, megabytes per
    /// band, which change only with the transfer function or the bands) followed by `tf`.
    /// `pre.0` is their generation: equal generations mean equal contents, so the large
    /// part is neither compared nor written again.
    pub fn sync_frame_tables(
        &mut self,
        transparent: &[u32],
        levels: &[[u32; 4]],
        pre: (u64, &[[f32; 4]]),
        tf: &[[f32; 4]],
        hbounds: &[[f32; 2]],
    ) {
        fn sync<T: bytemuck::Pod + PartialEq>(
            device: &wgpu::Device,
            queue: &wgpu::Queue,
            buf: &mut Grow,
            mirror: &mut Vec<T>,
            data: &[T],
            uploaded: &mut u64,
        ) {
            let fresh = buf.ensure(device, std::mem::size_of_val(data) as u64);
            if fresh || mirror.as_slice() != data {
                if !data.is_empty() {
                    queue.write_buffer(buf.get(), 0, bytemuck::cast_slice(data));
                }
                *mirror = data.to_vec();
                *uploaded += std::mem::size_of_val(data) as u64;
            }
        }
        let (d, q) = (&self.device, &self.queue);
        sync(
            d,
            q,
            &mut self.transparent,
            &mut self.transparent_mirror,
            transparent,
            &mut self.uploaded,
        );
        sync(
            d,
            q,
            &mut self.levels,
            &mut self.levels_mirror,
            levels,
            &mut self.uploaded,
        );
        let (generation, pre) = pre;
        let fresh = self.tf.ensure(
            d,
            std::mem::size_of_val(pre) as u64 + std::mem::size_of_val(tf) as u64,
        );
        let pre_same = !fresh && self.tf_pre == Some((generation, pre.len()));
        if !pre_same {
            if !pre.is_empty() {
                q.write_buffer(self.tf.get(), 0, bytemuck::cast_slice(pre));
            }
            self.tf_pre = Some((generation, pre.len()));
            self.uploaded += std::mem::size_of_val(pre) as u64;
        }
        if !pre_same || self.tf_mirror.as_slice() != tf {
            if !tf.is_empty() {
                q.write_buffer(
                    self.tf.get(),
                    std::mem::size_of_val(pre) as u64,
                    bytemuck::cast_slice(tf),
                );
            }
            self.tf_mirror.clear();
            self.tf_mirror.extend_from_slice(tf);
            self.uploaded += std::mem::size_of_val(tf) as u64;
        }
        sync(
            d,
            q,
            &mut self.hbounds,
            &mut self.hbounds_mirror,
            hbounds,
            &mut self.uploaded,
        );
    }

    /// Bytes written to the device (pages, tables) since the last call.
    pub fn take_uploaded(&mut self) -> u64 {
        std::mem::take(&mut self.uploaded)
    }

    fn pipeline(&mut self, compiled: EffectSet) -> Result<wgpu::ComputePipeline> {
        let hw = self.tex.is_some();
        let effects = pipeline_effects(compiled);
        let key = (effects, self.pool_bits, hw);
        let on = |e| if effects.contains(e) { 1.0 } else { 0.0 };
        if let Some(p) = self.pipelines.get(&key) {
            return Ok(p.clone());
        }
        let (device, module) = (&self.device, &self.module);
        let p = checked(device, "building a cast pipeline", || {
            let constants = [
                ("SHADING", on(EffectSet::SHADING)),
                ("MULTI", on(EffectSet::VOLUMES)),
                ("HORIZONS", on(EffectSet::HORIZONS)),
                ("LIGHTING", on(EffectSet::LIGHTING)),
                ("POOL_BITS", self.pool_bits as f64),
                ("HW_FILTER", if hw { 1.0 } else { 0.0 }),
                ("SLICES", on(EffectSet::SLICES)),
                ("PRE", on(EffectSet::PREINTEGRATED)),
            ];
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("cast"),
                layout: None,
                module,
                entry_point: Some("cast_rays"),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants: &constants,
                    ..Default::default()
                },
                cache: None,
            })
        })?;
        self.pipelines.insert(key, p.clone());
        Ok(p)
    }

    /// Casts one frame and reads back its pixels, feedback and counters. The tables must
    /// have been synced ([`sync_table`](Self::sync_table),
    /// [`sync_frame_tables`](Self::sync_frame_tables)) and the pools allocated.
    pub fn cast(
        &mut self,
        frame: &FrameParams,
        vols: &[VolumeParams],
        hors: &[HorizonParams],
        compiled: EffectSet,
        occl: Option<&[f32]>,
    ) -> Result<GpuCast> {
        if vols.len() > MAX_VOLUMES || hors.len() > MAX_HORIZONS || vols.len() + hors.len() == 0 {
            bail!(
                "the GPU caster renders up to {MAX_VOLUMES} volumes and {MAX_HORIZONS} horizons, \
                 at least one of either; the frame has {} and {}",
                vols.len(),
                hors.len()
            );
        }
        if self.table.buf.is_none() || self.tf.buf.is_none() {
            bail!("GPU caster: the tables must be uploaded before a frame");
        }
        if (!vols.is_empty() && self.pool.buf.is_none() && self.tex.is_none())
            || (!hors.is_empty() && self.hpool.buf.is_none())
        {
            bail!("GPU caster: the pools must be allocated before a frame");
        }
        // Every binding needs a buffer, used or not.
        for g in [
            &mut self.pool,
            &mut self.hpool,
            &mut self.hbounds,
            &mut self.occl,
        ] {
            g.ensure(&self.device, 16);
        }
        if let Some(o) = occl {
            if frame.occl_block == 0 {
                bail!("GPU caster: per-ray limits without a block size");
            }
            // Bound whole (the image is banded, its block rows are not): past the adapter's
            // largest storage binding, the frame would fail binding it without saying why.
            let bytes = std::mem::size_of_val(o) as u64;
            let max = self.device.limits().max_storage_buffer_binding_size;
            if bytes > max {
                bail!(
                    "GPU caster: occlusion's per-block limits for this frame take {bytes} bytes, \
                     past the adapter's largest storage binding ({max}): raise \
                     cluster.occlusion_block, or render this size on the CPU"
                );
            }
            self.occl.ensure(&self.device, bytes);
            self.queue
                .write_buffer(self.occl.get(), 0, bytemuck::cast_slice(o));
            self.uploaded += std::mem::size_of_val(o) as u64;
        }
        // The frame's pixels are one storage binding and its rows and columns one dispatch:
        // a region past either limit is cast in bands, each its own dispatch and binding.
        // Every ray reads its pixel's absolute position (`rect_x + gid.x`), so a band casts
        // exactly the rays the whole region would.
        let (band_w, band_h) = self.band_size(frame.rect_w, frame.rect_h);
        if band_w >= frame.rect_w && band_h >= frame.rect_h {
            return self.cast_band(frame, vols, hors, compiled);
        }
        let (w, h) = (frame.rect_w as usize, frame.rect_h as usize);
        let mut whole = GpuCast {
            pixels: vec![[0.0; 4]; w * h],
            feedback: Vec::new(),
            samples: 0,
            skipped: 0,
            terminated: 0,
            rays: 0,
            hits: 0,
            readback_bytes: 0,
            feedback_bytes: 0,
        };
        for by in (0..frame.rect_h).step_by(band_h as usize) {
            for bx in (0..frame.rect_w).step_by(band_w as usize) {
                let band = FrameParams {
                    rect_x: frame.rect_x + bx,
                    rect_y: frame.rect_y + by,
                    rect_w: band_w.min(frame.rect_w - bx),
                    rect_h: band_h.min(frame.rect_h - by),
                    ..*frame
                };
                let part = self.cast_band(&band, vols, hors, compiled)?;
                let bw = band.rect_w as usize;
                for (row, src) in part.pixels.chunks_exact(bw).enumerate() {
                    let at = (by as usize + row) * w + bx as usize;
                    whole.pixels[at..at + bw].copy_from_slice(src);
                }
                // Feedback counts per page-table entry: the engine sums repeated entries.
                whole.feedback.extend(part.feedback);
                whole.samples += part.samples;
                whole.skipped += part.skipped;
                whole.terminated += part.terminated;
                whole.rays += part.rays;
                whole.hits += part.hits;
                whole.readback_bytes += part.readback_bytes;
                whole.feedback_bytes += part.feedback_bytes;
            }
        }
        self.bands_cast += 1;
        Ok(whole)
    }

    /// The largest band, in pixels `(w, h)`, that one cast of a `rect_w × rect_h` region may
    /// have on this adapter ([`band_shape`] with its binding, the test cap
    /// [`set_band_pixels`](Self::set_band_pixels), and its dispatch side).
    fn band_size(&self, rect_w: u32, rect_h: u32) -> (u32, u32) {
        let side = self.limits.max_compute_workgroups_per_dimension as u64 * WORKGROUP as u64;
        band_shape(rect_w, rect_h, self.max_frame_pixels(), side)
    }

    /// Caps the pixels of one cast's band below what the adapter binds (`None`: the
    /// adapter's limit), so that tests can band frames of any size.
    pub fn set_band_pixels(&mut self, cap: Option<u64>) {
        self.band_cap = cap;
    }

    /// Regions cast in more than one band since the caster was made.
    pub fn banded_regions(&self) -> u64 {
        self.bands_cast
    }

    /// Casts one band: a region within the adapter's binding and dispatch limits.
    fn cast_band(
        &mut self,
        frame: &FrameParams,
        vols: &[VolumeParams],
        hors: &[HorizonParams],
        compiled: EffectSet,
    ) -> Result<GpuCast> {
        let px = frame.rect_w as u64 * frame.rect_h as u64;
        // What the frame's tables need the pipeline to have. (Several volumes need `MULTI`
        // only where one is marched, which the engine's effects say: without it the
        // pipeline marches no volume of a multi-volume frame.)
        let needs = EffectSet::NONE
            .with_if(EffectSet::HORIZONS, !hors.is_empty())
            .with_if(EffectSet::SLICES, vols.iter().any(|v| v.n_slices > 0))
            .with_if(EffectSet::SHADING, frame.flags & FRAME_SHADING != 0)
            .with_if(
                EffectSet::PREINTEGRATED,
                vols.iter().any(|v| v.flags & VOLUME_PREINTEGRATED != 0),
            )
            .with_if(
                EffectSet::LIGHTING,
                hors.iter().any(|h| h.flags & HORIZON_LIGHTING != 0),
            );
        if !compiled.contains(needs) {
            bail!("GPU caster: the frame needs {needs}, the pipeline asked for has {compiled}");
        }
        let pipeline = self.pipeline(compiled)?;
        let out_bytes = px * 16;
        let clock = Instant::now();
        let device = &self.device;
        self.out.ensure(device, out_bytes);
        self.read.ensure(device, out_bytes.max(64));
        let queue = &self.queue;
        queue.write_buffer(&self.frame, 0, bytemuck::bytes_of(frame));
        if !vols.is_empty() {
            queue.write_buffer(&self.vols, 0, bytemuck::cast_slice(vols));
        }
        if !hors.is_empty() {
            queue.write_buffer(&self.hors, 0, bytemuck::cast_slice(hors));
        }
        queue.write_buffer(&self.stats, 0, &[0u8; 32]);
        queue.write_buffer(&self.fb_len, 0, &[0u8; 32]);
        fn entry(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
            wgpu::BindGroupEntry {
                binding,
                resource: buffer.as_entire_binding(),
            }
        }
        let entries = frame.fb_entries;
        let (group, compact_group) = checked(device, "binding the frame", || {
            let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("cast"),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &[
                    entry(0, &self.frame),
                    entry(1, &self.vols),
                    entry(2, self.levels.get()),
                    entry(3, self.table.get()),
                    entry(4, self.transparent.get()),
                    entry(5, self.tf.get()),
                    entry(6, self.pool.get()),
                    entry(7, self.feedback.get()),
                    entry(8, self.out.get()),
                    entry(9, &self.stats),
                    entry(12, &self.hors),
                    entry(13, self.hbounds.get()),
                    entry(17, self.occl.get()),
                    entry(14, self.hpool.get()),
                    wgpu::BindGroupEntry {
                        binding: 15,
                        resource: wgpu::BindingResource::TextureView(
                            self.tex.as_ref().map_or(&self.dummy_tex, |t| &t.view),
                        ),
                    },
                    wgpu::BindGroupEntry {
                        binding: 16,
                        resource: wgpu::BindingResource::Sampler(&self.sampler),
                    },
                ],
            });
            let fb_counts = wgpu::BindGroupEntry {
                binding: 7,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: self.feedback.get(),
                    offset: 0,
                    size: std::num::NonZeroU64::new(entries.max(1) as u64 * 4),
                }),
            };
            let compact_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("compact"),
                layout: &self.compact.get_bind_group_layout(0),
                entries: &[
                    fb_counts,
                    entry(10, self.fb_list.get()),
                    entry(11, &self.fb_len),
                ],
            });
            (group, compact_group)
        })?;
        checked(device, "dispatching the cast", || {
            let mut enc = device.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&pipeline);
                pass.set_bind_group(0, &group, &[]);
                pass.dispatch_workgroups(
                    frame.rect_w.div_ceil(WORKGROUP).max(1),
                    frame.rect_h.div_ceil(WORKGROUP).max(1),
                    1,
                );
                let groups = entries.max(1).div_ceil(COMPACT_WORKGROUP);
                let gx = groups.min(self.limits.max_compute_workgroups_per_dimension);
                pass.set_pipeline(&self.compact);
                pass.set_bind_group(0, &compact_group, &[]);
                pass.dispatch_workgroups(gx, groups.div_ceil(gx), 1);
            }
            // Counters and feedback length first: one small readback tells how much list to fetch.
            enc.copy_buffer_to_buffer(&self.stats, 0, self.read.get(), 0, 32);
            enc.copy_buffer_to_buffer(&self.fb_len, 0, self.read.get(), 32, 4);
            queue.submit([enc.finish()]);
        })?;
        let head: Vec<u32> = self.map_read(36)?;
        let stat64 = |i: usize| head[i] as u64 | (head[i + 1] as u64) << 32;
        let fb_n = head[8].min(entries) as u64;
        let fb_bytes = fb_n * 8;
        let read_bytes = out_bytes.max(fb_bytes);
        self.read.ensure(&self.device, read_bytes);
        let mut feedback = Vec::with_capacity(fb_n as usize);
        if fb_n > 0 {
            let list: Vec<u32> =
                self.copy_and_read(self.fb_list.get(), fb_bytes, "feedback list")?;
            feedback.extend(list.chunks_exact(2).map(|p| (p[0], p[1])));
        }
        let mut pixels = Vec::new();
        if out_bytes > 0 {
            let raw: Vec<f32> = self.copy_and_read(self.out.get(), out_bytes, "image")?;
            pixels = raw
                .chunks_exact(4)
                .map(|c| [c[0], c[1], c[2], c[3]])
                .collect();
        }
        tracing::trace!(ms = clock.elapsed().as_secs_f64() * 1e3, "gpu cast");
        Ok(GpuCast {
            pixels,
            feedback,
            samples: stat64(0),
            skipped: stat64(2),
            terminated: head[4] as u64,
            rays: head[5] as u64,
            hits: head[6] as u64,
            readback_bytes: 36 + fb_bytes + out_bytes,
            feedback_bytes: 4 + fb_bytes,
        })
    }

    /// Copies the first `bytes` of `src` into the readback buffer and reads them.
    fn copy_and_read<T: bytemuck::Pod>(
        &self,
        src: &wgpu::Buffer,
        bytes: u64,
        what: &str,
    ) -> Result<Vec<T>> {
        checked(&self.device, &format!("reading the {what}"), || {
            let mut enc = self.device.create_command_encoder(&Default::default());
            enc.copy_buffer_to_buffer(src, 0, self.read.get(), 0, bytes);
            self.queue.submit([enc.finish()]);
        })?;
        self.map_read(bytes)
    }

    /// Waits for the queue, maps the first `bytes` of the readback buffer and copies them out.
    fn map_read<T: bytemuck::Pod>(&self, bytes: u64) -> Result<Vec<T>> {
        let buf = self.read.get();
        let slice = buf.slice(0..bytes);
        let (tx, rx) = mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        let polled = self
            .device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| anyhow!("waiting for the device: {e}"));
        // Copied out and unmapped before any error returns: a buffer left mapped fails
        // every later copy into it, and the buffer is reused at the same size, so one
        // error (say, an earlier write's, reported here) would end the engine's GPU.
        let out = match rx.try_recv() {
            Ok(Ok(())) => {
                let out = slice
                    .get_mapped_range()
                    .context("readback mapped range")
                    .map(|view| bytemuck::cast_slice::<u8, T>(&view).to_vec());
                buf.unmap();
                out
            }
            Ok(Err(e)) => Err(anyhow!(e).context("mapping the readback buffer")),
            Err(_) => Err(anyhow!("the readback buffer's map callback did not run")),
        };
        polled?;
        self.check_uncaptured()?;
        out
    }

    fn check_uncaptured(&self) -> Result<()> {
        let mut slot = self.uncaptured.lock().unwrap_or_else(|p| p.into_inner());
        match slot.take() {
            Some(e) => bail!("wgpu error: {e}"),
            None => Ok(()),
        }
    }
}

/// The largest band `(w, h)` of a `rect_w × rect_h` region whose RGBA f32 output fits
/// `max_px` pixels (one storage binding) and whose sides fit `side` (one dispatch): the
/// region's width where one row fits both, else columns; as many rows as fit, rounded down to
/// whole workgroups where at least one workgroup's rows fit and the band is not the whole
/// region. Never 0.
fn band_shape(rect_w: u32, rect_h: u32, max_px: u64, side: u64) -> (u32, u32) {
    let side = side.clamp(1, u32::MAX as u64);
    let max_px = max_px.max(1);
    let w = (rect_w as u64).min(side).min(max_px).max(1) as u32;
    let mut h = (max_px / w as u64).min(side) as u32;
    if h < rect_h && h >= WORKGROUP {
        h -= h % WORKGROUP;
    }
    (w, h.min(rect_h).max(1))
}

/// Runs `f` inside validation and out-of-memory error scopes and turns what they caught into
/// an error: wgpu's default reaction to either is a panic.
fn checked<T>(device: &wgpu::Device, what: &str, f: impl FnOnce() -> T) -> Result<T> {
    let out_of_memory = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
    let validation = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let value = f();
    let validation = pollster::block_on(validation.pop());
    let out_of_memory = pollster::block_on(out_of_memory.pop());
    match validation.or(out_of_memory) {
        Some(e) => bail!("{what}: {e}"),
        None => Ok(value),
    }
}

#[cfg(test)]
mod tests {
    use super::{band_shape, ShrinkWindow, SHRINK_FLOOR, SHRINK_WINDOW, WORKGROUP};

    #[test]
    fn buffers_shrink_to_a_windows_largest_need() {
        let big = 256 << 20;
        let mut w = ShrinkWindow::default();
        // Small buffers stay, however little is asked.
        for _ in 0..3 * SHRINK_WINDOW {
            assert_eq!(w.observe(SHRINK_FLOOR, 16), None);
        }
        // A window of small calls shrinks at its end, and only there, to its largest need.
        let mut w = ShrinkWindow::default();
        for call in 1..=SHRINK_WINDOW {
            let need = if call == 7 { big / 4 } else { big / 64 };
            let got = w.observe(big, need);
            assert_eq!(
                got,
                (call == SHRINK_WINDOW).then_some(big / 4),
                "call {call}"
            );
        }
        assert_eq!(w, ShrinkWindow::default());
        // One call past a quarter anywhere in the window keeps the buffer.
        let mut w = ShrinkWindow::default();
        for call in 1..=SHRINK_WINDOW {
            let need = if call == 100 { big / 4 + 16 } else { big / 64 };
            assert_eq!(w.observe(big, need), None);
        }
        // Sizes alternating within a window (a large leaf and small ones, every frame)
        // never shrink.
        let mut w = ShrinkWindow::default();
        for call in 0..20 * SHRINK_WINDOW {
            let need = if call % 42 == 0 { big } else { big / 16 };
            assert_eq!(w.observe(big, need), None);
        }
    }

    #[test]
    fn bands_fit_one_binding_and_one_dispatch() {
        // Fits whole: one band.
        assert_eq!(band_shape(640, 480, 1 << 20, 1 << 19), (640, 480));
        // Rows as many as the binding holds, rounded down to whole workgroups.
        assert_eq!(band_shape(100, 1000, 100 * 37, 1 << 19), (100, 32));
        // Fewer rows than one workgroup fit: not rounded.
        assert_eq!(band_shape(100, 1000, 100 * 3 + 5, 1 << 19), (100, 3));
        // A row wider than one binding: columns, one row each.
        assert_eq!(band_shape(61, 37, 40, 1 << 19), (40, 1));
        // A row wider than one dispatch: columns of the dispatch side.
        assert_eq!(band_shape(2000, 10, 1 << 30, 512), (512, 10));
        // Rows past the dispatch side.
        assert_eq!(band_shape(10, 5000, 1 << 30, 512), (10, 512));
        // Every band of a region covers it exactly, within both limits.
        for (w, h, px, side) in [(61, 37, 491, 1 << 19), (1000, 999, 7777, 96), (1, 1, 1, 1)] {
            let (bw, bh) = band_shape(w, h, px, side);
            assert!(bw >= 1 && bh >= 1 && bw as u64 * bh as u64 <= px.max(bw as u64));
            assert!(bw as u64 <= side && bh as u64 <= side);
            assert!(bh == h || bh < WORKGROUP || bh % WORKGROUP == 0);
        }
    }
}
