//! Strata's volume ray march as a WGSL compute shader (wgpu).
//!
//! This is the GPU twin of the CPU caster: given the same [`VolumeJob`] it produces the same
//! image (to about 1e-4), so a benchmark can run both on one frame and compare them. On a
//! machine without a GPU, Mesa's software Vulkan driver (lavapipe,
//! `apt-get install mesa-vulkan-drivers libvulkan1`) or the GL driver llvmpipe provide an
//! adapter; [`GpuRayMarcher::is_software`] tells the two cases apart.
//!
//! # Algorithm
//!
//! For each pixel `(x, y)` (row 0 at the top, output index `y * width + x`):
//!
//! 1. `d = normalize(dir00 + (x + 0.5) * du + (y + 0.5) * dv)`; the ray is `p(t) = t * d`
//!    (camera-relative, origin 0).
//! 2. In index space `q(t) = c + t * (M * d)`; the ray is clipped to the volume box
//!    `[-0.5, dims - 0.5]` (slab method), giving `[t0, t1)` with `t0 >= 0`.
//! 3. Samples sit on the global lattice `t_k = k * step` (evaluated as `f32(k) * step`); sample
//!    `k` is taken iff `t0 <= t_k < t1`.
//! 4. If `brick > 0` and the cell `floor(clamp(q, 0, dims - 1) / brick)` is flagged
//!    transparent, the march jumps to the first lattice sample at or beyond the ray's exit
//!    from that cell's box `[cell * brick - 0.5, (cell + 1) * brick - 0.5]` (clipped to the
//!    volume box), and always at least one sample forward. Otherwise the volume is sampled
//!    trilinearly at `q` clamped to `[0, dims - 1]`.
//! 5. The transfer function maps `clamp((v - lo) / (hi - lo), 0, 1) * (N - 1)` linearly into
//!    the table; a positive alpha is corrected for the step length,
//!    `a = 1 - (1 - a)^alpha_exponent`, and composited front to back with premultiplied
//!    colour (`C += (1 - A) * a * rgb`, `A += (1 - A) * a`) until `A >= early_termination`.
//! 6. The pixel is `(C.r, C.g, C.b, A)`.
//!
//! Linear interpolation is `a * (1 - t) + b * t` everywhere (WGSL's definition of `mix`).
#![deny(missing_docs)]

mod device;
mod job;

pub use device::GpuRayMarcher;

/// One frame of a single dense volume, in the form both the CPU caster and the shader take.
///
/// Positions are camera-relative: the eye sits at the origin, which keeps f32 coordinates
/// small for surveys that lie far from their CRS origin.
#[derive(Clone, Copy, Debug)]
pub struct VolumeJob<'a> {
    /// Volume size in voxels. Voxel `(x, y, z)` is `voxels[(z * dims[1] + y) * dims[0] + x]`
    /// (x fastest) and its centre is at index coordinates `(x, y, z)`.
    pub dims: [u32; 3],
    /// `dims[0] * dims[1] * dims[2]` finite values. No-data (NaN) must be replaced by the
    /// caller with a value the transfer function maps to alpha 0: WGSL allows a shader to
    /// assume that NaN never occurs, so NaN could not be handled identically on both sides.
    pub voxels: &'a [f32],
    /// Affine map to index space, as three rows `[m_x, m_y, m_z, c]`:
    /// `index = M * p + c` for a camera-relative position `p`. `M` must be invertible.
    pub world_to_index: [[f32; 4]; 3],
    /// Transfer function table: straight (non-premultiplied) RGBA with alpha in `[0, 1]`
    /// for a step of the reference length. Must not be empty.
    pub tf: &'a [[f32; 4]],
    /// Values `tf_range[0] ..= tf_range[1]` map to table positions `0 ..= N - 1`; values
    /// outside are clamped. The two ends must differ.
    pub tf_range: [f32; 2],
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Unnormalised direction through the corner of pixel (0, 0) (top left), camera-relative.
    pub dir00: [f32; 3],
    /// Direction increment per pixel to the right.
    pub du: [f32; 3],
    /// Direction increment per pixel downwards.
    pub dv: [f32; 3],
    /// Distance between samples along the normalised ray, in camera-relative units.
    pub step: f32,
    /// Opacity correction exponent `step / reference_step` (1.0 skips the correction).
    pub alpha_exponent: f32,
    /// Stop a ray once its accumulated alpha reaches this, in `(0, 1]` (1.0 stops only at
    /// full opacity).
    pub early_termination: f32,
    /// Empty-space-skipping cell edge in voxels (for example 8 or 64); 0 disables skipping.
    pub brick: u32,
    /// One flag per cell of the `ceil(dims / brick)` grid, x fastest; nonzero means every
    /// sample inside the cell's box maps to alpha 0, so the march may jump over it. Flags must
    /// be conservative (see the test for a margin-based construction). Ignored if `brick == 0`.
    pub transparent: &'a [u32],
}

/// The result of [`GpuRayMarcher::render`].
#[derive(Clone, Debug, Default)]
pub struct GpuFrame {
    /// Premultiplied RGBA per pixel, row-major from the top row (`y * width + x`).
    pub rgba: Vec<[f32; 4]>,
    /// Host-to-device transfer of the volume (only when it changed), the transfer function,
    /// the flags and the parameters, until the device has finished the copies.
    pub upload_ms: f64,
    /// Dispatch of the ray march until the device has finished it.
    pub kernel_ms: f64,
    /// Copy of the image into a mappable buffer, mapping and reading it back.
    pub readback_ms: f64,
}
