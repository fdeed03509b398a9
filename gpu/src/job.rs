//! Input validation and the uniform block the shader reads.
//!
//! Everything that could make the shader index out of bounds, loop without end, or hit a
//! case where WGSL and Rust may legally disagree (NaN, inf, division by zero) is rejected here
//! with an error, so `render` never panics and never returns an image that silently differs
//! from the CPU caster.

use anyhow::{bail, ensure, Result};
use bytemuck::{Pod, Zeroable};

use crate::VolumeJob;

/// Workgroup edge; must match `@workgroup_size(8, 8, 1)` in raymarch.wgsl.
pub(crate) const WORKGROUP: u32 = 8;

/// The shader's `Params`. WGSL aligns `vec4` uniform members to 16 bytes, so every field is a
/// 4-vector and scalars ride in spare `w` lanes; the layout then matches `#[repr(C)]` exactly.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub(crate) struct Params {
    m0: [f32; 4],
    m1: [f32; 4],
    m2: [f32; 4],
    dir00: [f32; 4],
    du: [f32; 4],
    dv: [f32; 4],
    tf_range: [f32; 4],
    dims: [u32; 4],
    cells: [u32; 4],
    image: [u32; 4],
}

/// A validated job: the uniform block plus the buffer sizes the device needs.
#[derive(Debug)]
pub(crate) struct Prepared {
    pub(crate) params: Params,
    /// Number of transparency flags the shader may read (0 without skipping).
    pub(crate) flag_count: usize,
    /// Bytes of the RGBA32F output image.
    pub(crate) out_bytes: u64,
}

/// Largest lattice index the march may reach: `f32(k)` is exact only up to 2^24, beyond which
/// consecutive samples would collapse onto the same distance.
const MAX_LATTICE_INDEX: f64 = (1u64 << 24) as f64;

/// Checks `job` against the rules in the crate docs and the device limits (everything except
/// the voxel values, which are checked once per upload by [`check_voxels`]).
pub(crate) fn prepare(job: &VolumeJob<'_>, limits: &wgpu::Limits) -> Result<Prepared> {
    let [nx, ny, nz] = job.dims;
    ensure!(
        nx > 0 && ny > 0 && nz > 0,
        "volume dims {:?} must all be positive",
        job.dims
    );
    let voxel_count = nx as u64 * ny as u64 * nz as u64;
    // The shader computes voxel indices in u32.
    ensure!(
        voxel_count <= u32::MAX as u64,
        "volume of {voxel_count} voxels exceeds the shader's 32-bit index range"
    );
    ensure!(
        job.voxels.len() as u64 == voxel_count,
        "volume has {} values, dims {:?} need {voxel_count}",
        job.voxels.len(),
        job.dims
    );
    check_binding("volume", voxel_count * 4, limits)?;

    ensure!(
        job.world_to_index.iter().flatten().all(|v| v.is_finite()),
        "world_to_index is not finite"
    );
    let m = job
        .world_to_index
        .map(|r| [r[0] as f64, r[1] as f64, r[2] as f64]);
    let inv = invert3(m).ok_or_else(|| anyhow::anyhow!("world_to_index is singular"))?;

    ensure!(!job.tf.is_empty(), "transfer function table is empty");
    ensure!(
        job.tf.len() <= u32::MAX as usize,
        "transfer function table too long"
    );
    check_binding("transfer function", job.tf.len() as u64 * 16, limits)?;
    for (i, e) in job.tf.iter().enumerate() {
        ensure!(
            e.iter().all(|v| v.is_finite()),
            "transfer function entry {i} is not finite"
        );
        // 1 - alpha must stay in [0, 1] for the opacity correction's pow.
        ensure!(
            (0.0..=1.0).contains(&e[3]),
            "transfer function alpha {} at {i} is outside [0, 1]",
            e[3]
        );
    }
    let [lo, hi] = job.tf_range;
    ensure!(
        lo.is_finite() && hi.is_finite() && lo != hi,
        "tf_range {:?} must be finite and non-empty",
        job.tf_range
    );
    ensure!(
        (hi - lo).is_finite(),
        "tf_range {:?} overflows f32",
        job.tf_range
    );

    ensure!(
        job.width > 0 && job.height > 0,
        "image size {}x{} is empty",
        job.width,
        job.height
    );
    let groups = limits.max_compute_workgroups_per_dimension;
    ensure!(
        job.width.div_ceil(WORKGROUP) <= groups && job.height.div_ceil(WORKGROUP) <= groups,
        "image {}x{} needs more than {groups} workgroups per dimension",
        job.width,
        job.height
    );
    let pixels = job.width as u64 * job.height as u64;
    ensure!(
        pixels <= u32::MAX as u64,
        "image of {pixels} pixels exceeds the shader's 32-bit index range"
    );
    let out_bytes = pixels * 16;
    check_binding("output image", out_bytes, limits)?;

    ensure!(
        job.dir00
            .iter()
            .chain(&job.du)
            .chain(&job.dv)
            .all(|v| v.is_finite()),
        "ray directions are not finite"
    );
    ensure!(
        job.step.is_finite() && job.step > 0.0,
        "step {} must be positive",
        job.step
    );
    ensure!(
        job.alpha_exponent.is_finite() && job.alpha_exponent > 0.0,
        "alpha_exponent {} must be positive",
        job.alpha_exponent
    );
    ensure!(
        job.early_termination > 0.0 && job.early_termination <= 1.0,
        "early_termination {} must be in (0, 1]",
        job.early_termination
    );

    // Every lattice index the march can reach is at most (farthest box corner) / step.
    let far = box_corners(job.dims)
        .map(|q| {
            let c = job.world_to_index.map(|r| r[3] as f64);
            let p = mul3(inv, [q[0] - c[0], q[1] - c[1], q[2] - c[2]]);
            (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
        })
        .fold(0.0f64, f64::max);
    if far / job.step as f64 + 2.0 > MAX_LATTICE_INDEX {
        bail!(
            "step {} is too small for a volume up to {far:.3} away: more than 2^24 lattice steps",
            job.step
        );
    }

    let (cells, flag_count) = if job.brick > 0 {
        let cells = job.dims.map(|n| n.div_ceil(job.brick));
        let count = cells.iter().map(|&c| c as usize).product::<usize>();
        ensure!(
            job.transparent.len() == count,
            "{} transparency flags given, {cells:?} cells of {} voxels need {count}",
            job.transparent.len(),
            job.brick
        );
        check_binding("transparency flags", count as u64 * 4, limits)?;
        (cells, count)
    } else {
        ([0; 3], 0)
    };

    let with_w = |v: [f32; 3], w: f32| [v[0], v[1], v[2], w];
    let params = Params {
        m0: job.world_to_index[0],
        m1: job.world_to_index[1],
        m2: job.world_to_index[2],
        dir00: with_w(job.dir00, job.step),
        du: with_w(job.du, job.alpha_exponent),
        dv: with_w(job.dv, job.early_termination),
        tf_range: [lo, hi, 0.0, 0.0],
        dims: [nx, ny, nz, job.brick],
        cells: [cells[0], cells[1], cells[2], job.tf.len() as u32],
        image: [job.width, job.height, 0, 0],
    };
    Ok(Prepared {
        params,
        flag_count,
        out_bytes,
    })
}

/// Rejects non-finite voxels (see [`VolumeJob::voxels`]). Run once per upload, not per frame.
pub(crate) fn check_voxels(voxels: &[f32]) -> Result<()> {
    if let Some(i) = voxels.iter().position(|v| !v.is_finite()) {
        bail!(
            "voxel {i} is {} (replace no-data with a value that maps to alpha 0)",
            voxels[i]
        );
    }
    Ok(())
}

fn check_binding(what: &str, bytes: u64, limits: &wgpu::Limits) -> Result<()> {
    let max = limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size);
    ensure!(
        bytes <= max,
        "{what} needs {bytes} bytes ({:.1} MiB) but this adapter binds at most {max} bytes ({:.1} MiB) per storage buffer",
        bytes as f64 / 1048576.0,
        max as f64 / 1048576.0
    );
    Ok(())
}

fn box_corners(dims: [u32; 3]) -> impl Iterator<Item = [f64; 3]> {
    (0..8).map(move |i| {
        let end = |axis: usize| {
            if i >> axis & 1 == 0 {
                -0.5
            } else {
                dims[axis] as f64 - 0.5
            }
        };
        [end(0), end(1), end(2)]
    })
}

fn mul3(m: [[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    m.map(|r| r[0] * v[0] + r[1] * v[1] + r[2] * v[2])
}

fn invert3(m: [[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let cof =
        |r0: usize, r1: usize, c0: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    let det = m[0][0] * cof(1, 2, 1, 2) - m[0][1] * cof(1, 2, 0, 2) + m[0][2] * cof(1, 2, 0, 1);
    let scale = m.iter().flatten().fold(0.0f64, |a, v| a.max(v.abs()));
    if !det.is_finite() || det.abs() <= 1e-12 * scale * scale * scale {
        return None;
    }
    let inv = 1.0 / det;
    Some([
        [
            cof(1, 2, 1, 2) * inv,
            -cof(0, 2, 1, 2) * inv,
            cof(0, 1, 1, 2) * inv,
        ],
        [
            -cof(1, 2, 0, 2) * inv,
            cof(0, 2, 0, 2) * inv,
            -cof(0, 1, 0, 2) * inv,
        ],
        [
            cof(1, 2, 0, 1) * inv,
            -cof(0, 2, 0, 1) * inv,
            cof(0, 1, 0, 1) * inv,
        ],
    ])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn params_layout_matches_wgsl() {
        // Ten vec4 members of 16 bytes each, no implicit padding.
        assert_eq!(std::mem::size_of::<Params>(), 160);
    }

    #[test]
    fn inverse_is_inverse() {
        let m = [[0.5, 0.2, 0.0], [-0.1, 1.5, 0.3], [0.0, 0.4, 2.0]];
        let inv = invert3(m).unwrap();
        let product: [[f64; 3]; 3] = std::array::from_fn(|i| {
            std::array::from_fn(|j| (0..3).map(|k| m[i][k] * inv[k][j]).sum())
        });
        for (i, row) in product.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                assert!(
                    (v - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12,
                    "{product:?}"
                );
            }
        }
        assert!(invert3([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]]).is_none());
    }
}
