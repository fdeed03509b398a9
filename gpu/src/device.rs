//! The wgpu device, the compute pipeline and the buffers it keeps between frames.

use std::sync::{mpsc, Arc, Mutex};
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};

use crate::job::{self, Prepared, WORKGROUP};
use crate::{GpuFrame, VolumeJob};

const SHADER: &str = include_str!("raymarch.wgsl");

/// Runs the WGSL ray march (see the crate docs) on one wgpu adapter.
///
/// The volume buffer is kept between calls to [`render`](Self::render) and uploaded again only
/// when the job's volume changes identity (dims, slice address or length), so a benchmark can
/// time repeated frames without paying for the upload each time.
pub struct GpuRayMarcher {
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    limits: wgpu::Limits,
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    params: wgpu::Buffer,
    volume: Option<CachedVolume>,
    tf: Option<wgpu::Buffer>,
    flags: Option<wgpu::Buffer>,
    output: Option<OutputBuffers>,
    /// Errors that escaped every error scope (wgpu's default handler would panic on them).
    uncaptured: Arc<Mutex<Option<String>>>,
}

/// The uploaded volume and what identifies the slice it came from.
struct CachedVolume {
    dims: [u32; 3],
    ptr: usize,
    len: usize,
    buffer: wgpu::Buffer,
}

/// The shader's output and the mappable copy the host reads, both `bytes` long.
struct OutputBuffers {
    bytes: u64,
    storage: wgpu::Buffer,
    staging: wgpu::Buffer,
}

impl GpuRayMarcher {
    /// Opens the preferred adapter (a discrete GPU if there is one, otherwise whatever exists,
    /// such as lavapipe) and builds the pipeline. The instance honours `WGPU_BACKEND`
    /// (`vulkan`, `gl`). Fails, without panicking, if there is no adapter with compute shaders.
    pub fn new() -> Result<Self> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
            ..Default::default()
        }))
        .map_err(|e| {
            anyhow!(
                "no wgpu adapter: {e} (without a GPU, `apt-get install mesa-vulkan-drivers libvulkan1` provides lavapipe)"
            )
        })?;
        let info = adapter.get_info();
        if !adapter
            .get_downlevel_capabilities()
            .flags
            .contains(wgpu::DownlevelFlags::COMPUTE_SHADERS)
        {
            bail!(
                "adapter {} ({:?}) has no compute shaders",
                info.name,
                info.backend
            );
        }
        // The adapter's own limits, not the WebGPU defaults: those cap a storage binding at
        // 128 MiB and a buffer at 256 MiB regardless of what the hardware can do.
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("strata-gpu"),
            required_features: wgpu::Features::empty(),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .with_context(|| format!("request_device on {} ({:?})", info.name, info.backend))?;

        let uncaptured = Arc::new(Mutex::new(None));
        let sink = uncaptured.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            let mut slot = sink.lock().unwrap_or_else(|p| p.into_inner());
            slot.get_or_insert_with(|| e.to_string());
        }));

        let (pipeline, layout, params) =
            checked(&device, "building the ray-march pipeline", || {
                let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some("raymarch.wgsl"),
                    source: wgpu::ShaderSource::Wgsl(SHADER.into()),
                });
                // The layout is derived from the shader, which is the single source of truth for
                // the bindings.
                let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some("raymarch"),
                    layout: None,
                    module: &module,
                    entry_point: Some("main"),
                    compilation_options: Default::default(),
                    cache: None,
                });
                let layout = pipeline.get_bind_group_layout(0);
                let params = device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("params"),
                    size: std::mem::size_of::<job::Params>() as u64,
                    usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                });
                (pipeline, layout, params)
            })?;

        Ok(Self {
            device,
            queue,
            info,
            limits,
            pipeline,
            layout,
            params,
            volume: None,
            tf: None,
            flags: None,
            output: None,
            uncaptured,
        })
    }

    /// The adapter's name and backend, e.g. `llvmpipe (LLVM 15.0.6, 256 bits) (Vulkan)`.
    pub fn adapter_name(&self) -> String {
        format!("{} ({:?})", self.info.name, self.info.backend)
    }

    /// True if the adapter is a CPU implementation (lavapipe, llvmpipe, WARP), so that a
    /// benchmark does not mistake it for GPU numbers.
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// Ray-marches one frame and reads it back.
    ///
    /// The volume is recognised by its dims, slice address and length only: after changing
    /// voxel values in place (or freeing a volume and getting a new one at the same address),
    /// create a new marcher or render another volume once, or the old data will be used.
    ///
    /// Returns an error (never panics) for invalid jobs (see [`VolumeJob`]), for buffers larger
    /// than the adapter can bind, and for device failures.
    pub fn render(&mut self, job: &VolumeJob<'_>) -> Result<GpuFrame> {
        let prepared = job::prepare(job, &self.limits)?;
        let same_volume = self.volume.as_ref().is_some_and(|v| {
            v.dims == job.dims && v.ptr == job.voxels.as_ptr() as usize && v.len == job.voxels.len()
        });
        if !same_volume {
            // Validation, not transfer: kept out of upload_ms.
            job::check_voxels(job.voxels)?;
        }
        let clock = Instant::now();
        let bind_group = self.upload(job, &prepared, same_volume)?;
        let upload_ms = ms_since(clock);

        let clock = Instant::now();
        checked(&self.device, "dispatching the ray march", || {
            let mut encoder = self.device.create_command_encoder(&Default::default());
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("raymarch"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(&self.pipeline);
                pass.set_bind_group(0, &bind_group, &[]);
                pass.dispatch_workgroups(
                    job.width.div_ceil(WORKGROUP),
                    job.height.div_ceil(WORKGROUP),
                    1,
                );
            }
            self.queue.submit([encoder.finish()]);
        })?;
        self.wait()?;
        let kernel_ms = ms_since(clock);

        let clock = Instant::now();
        let rgba = self.read_back()?;
        let readback_ms = ms_since(clock);
        self.check_uncaptured()?;
        Ok(GpuFrame {
            rgba,
            upload_ms,
            kernel_ms,
            readback_ms,
        })
    }

    /// Brings every input buffer up to date, waits for the copies, and binds them.
    fn upload(
        &mut self,
        job: &VolumeJob<'_>,
        prepared: &Prepared,
        same_volume: bool,
    ) -> Result<wgpu::BindGroup> {
        let (device, queue) = (&self.device, &self.queue);
        if !same_volume {
            // Free the old volume first: two large volumes may not fit at once.
            self.volume = None;
            let buffer = checked(device, "uploading the volume", || {
                let bytes: &[u8] = bytemuck::cast_slice(job.voxels);
                let buffer = device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("volume"),
                    size: bytes.len() as u64,
                    usage: wgpu::BufferUsages::STORAGE,
                    mapped_at_creation: true,
                });
                buffer
                    .slice(..)
                    .get_mapped_range_mut()
                    .map(|mut view| view.copy_from_slice(bytes))?;
                buffer.unmap();
                Ok::<_, anyhow::Error>(buffer)
            })??;
            self.volume = Some(CachedVolume {
                dims: job.dims,
                ptr: job.voxels.as_ptr() as usize,
                len: job.voxels.len(),
                buffer,
            });
        }

        let tf = bytemuck::cast_slice(job.tf);
        // A binding may not be empty, so "no skipping" still binds one (unused) flag.
        let flags: &[u8] = if prepared.flag_count > 0 {
            bytemuck::cast_slice(job.transparent)
        } else {
            &[0; 4]
        };
        let out_bytes = prepared.out_bytes;
        let bind_group = checked(device, "uploading frame inputs", || {
            write_growing(device, queue, &mut self.tf, "transfer function", tf);
            write_growing(device, queue, &mut self.flags, "transparency flags", flags);
            queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&prepared.params));
            if self.output.as_ref().is_none_or(|o| o.bytes != out_bytes) {
                drop(self.output.take()); // free before allocating the new pair
                self.output = Some(OutputBuffers::new(device, out_bytes));
            }
            fn entry(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
                wgpu::BindGroupEntry {
                    binding,
                    resource: buffer.as_entire_binding(),
                }
            }
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("raymarch"),
                layout: &self.layout,
                entries: &[
                    entry(0, &self.params),
                    entry(1, &self.volume.as_ref().expect("uploaded above").buffer),
                    entry(2, self.tf.as_ref().expect("written above")),
                    entry(3, self.flags.as_ref().expect("written above")),
                    entry(4, &self.output.as_ref().expect("allocated above").storage),
                ],
            })
        })?;
        // An empty submission flushes the queued writes, so upload time ends when the data is
        // on the device rather than being billed to the kernel.
        queue.submit([]);
        self.wait()?;
        Ok(bind_group)
    }

    /// Copies the image to the mappable buffer and reads it.
    fn read_back(&self) -> Result<Vec<[f32; 4]>> {
        let out = self.output.as_ref().context("no output buffer")?;
        checked(&self.device, "reading back the image", || {
            let mut encoder = self.device.create_command_encoder(&Default::default());
            encoder.copy_buffer_to_buffer(&out.storage, 0, &out.staging, 0, out.bytes);
            self.queue.submit([encoder.finish()]);
        })?;
        let (tx, rx) = mpsc::channel();
        let slice = out.staging.slice(..);
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.wait()?;
        rx.recv()
            .context("map callback did not run")?
            .context("mapping the image for reading")?;
        let rgba = {
            let view = slice.get_mapped_range().context("image mapped range")?;
            bytemuck::cast_slice::<u8, [f32; 4]>(&view).to_vec()
        };
        out.staging.unmap();
        Ok(rgba)
    }

    /// Blocks until everything submitted so far has finished on the device.
    fn wait(&self) -> Result<()> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| anyhow!("waiting for the device: {e}"))?;
        self.check_uncaptured()
    }

    fn check_uncaptured(&self) -> Result<()> {
        let mut slot = self.uncaptured.lock().unwrap_or_else(|p| p.into_inner());
        match slot.take() {
            Some(e) => bail!("wgpu error: {e}"),
            None => Ok(()),
        }
    }
}

impl OutputBuffers {
    fn new(device: &wgpu::Device, bytes: u64) -> Self {
        let buffer = |label, usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes,
                usage,
                mapped_at_creation: false,
            })
        };
        Self {
            bytes,
            storage: buffer(
                "image",
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            ),
            staging: buffer(
                "image readback",
                wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            ),
        }
    }
}

/// Writes `data` into the storage buffer in `slot`, replacing it only when it is too small.
/// The shader knows the real lengths from the parameters, so a larger buffer is harmless.
fn write_growing(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    slot: &mut Option<wgpu::Buffer>,
    label: &str,
    data: &[u8],
) {
    if slot.as_ref().is_none_or(|b| b.size() < data.len() as u64) {
        *slot = Some(device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: data.len() as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        }));
    }
    queue.write_buffer(slot.as_ref().expect("allocated above"), 0, data);
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

fn ms_since(start: Instant) -> f64 {
    start.elapsed().as_secs_f64() * 1e3
}
