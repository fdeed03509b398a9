//! Sources of gridded samples that the store builder reads from.
//!
//! A source is anything that can fill an axis-aligned box of `f32` samples (`NaN` =
//! no-data): a raw file, a SEG-Y file through its trace index, a synthetic survey, or the
//! previous level of a store being built. The builder asks for boxes shaped as rows of
//! bricks along the source's contiguous axis, so each source reads long contiguous runs.

use anyhow::{bail, Context, Result};
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use strata_common::sample::SampleType;

/// Something that can fill boxes of samples.
pub trait GridSource: Sync {
    /// Samples per axis.
    fn dims(&self) -> [u64; 3];
    /// The axis along which the source's samples are contiguous (0 = x).
    fn contiguous_axis(&self) -> usize;
    /// Fills `out` (x fastest, `size[0]·size[1]·size[2]` values) with the box that starts at
    /// `lo` and has `size` samples per axis. The box lies inside `dims()`. `NaN` = no-data.
    fn read_box(&self, lo: [u64; 3], size: [u64; 3], out: &mut [f32]) -> Result<()>;
}

/// A headerless raw volume file, x fastest, then y, then z.
pub struct RawSource {
    path: PathBuf,
    file: File,
    dims: [u64; 3],
    dtype: SampleType,
    big_endian: bool,
}

impl RawSource {
    /// Opens `path` and checks that its size matches `dims` and `dtype` exactly.
    pub fn open(path: &Path, dims: [u64; 3], dtype: SampleType, big_endian: bool) -> Result<Self> {
        let file = File::open(path).with_context(|| format!("{}: cannot open", path.display()))?;
        let len = file
            .metadata()
            .with_context(|| format!("{}: cannot stat", path.display()))?
            .len();
        let want = dims
            .iter()
            .try_fold(dtype.size() as u64, |a, &d| a.checked_mul(d))
            .with_context(|| {
                format!(
                    "{}: dimensions {dims:?} of {} samples overflow a 64-bit byte count",
                    path.display(),
                    dtype.name()
                )
            })?;
        if dims.contains(&0) {
            bail!(
                "{}: dimensions must be at least 1, got {:?}",
                path.display(),
                dims
            );
        }
        if len != want {
            bail!(
                "{}: file has {len} bytes, expected {want} = {} x {} x {} x {} bytes ({}); check --dims and --dtype",
                path.display(),
                dims[0],
                dims[1],
                dims[2],
                dtype.size(),
                dtype.name()
            );
        }
        Ok(RawSource {
            path: path.to_path_buf(),
            file,
            dims,
            dtype,
            big_endian,
        })
    }
}

impl GridSource for RawSource {
    fn dims(&self) -> [u64; 3] {
        self.dims
    }
    fn contiguous_axis(&self) -> usize {
        0
    }
    fn read_box(&self, lo: [u64; 3], size: [u64; 3], out: &mut [f32]) -> Result<()> {
        let es = self.dtype.size();
        let row = size[0] as usize;
        let mut buf = vec![0u8; row * es];
        for z in 0..size[2] {
            for y in 0..size[1] {
                let idx = ((lo[2] + z) * self.dims[1] + lo[1] + y) * self.dims[0] + lo[0];
                let off = idx * es as u64;
                self.file.read_exact_at(&mut buf, off).with_context(|| {
                    format!(
                        "{}: read of {} bytes at byte {off} failed",
                        self.path.display(),
                        buf.len()
                    )
                })?;
                if self.big_endian && es > 1 {
                    buf.chunks_exact_mut(es).for_each(|c| c.reverse());
                }
                let o = ((z * size[1] + y) as usize) * row;
                self.dtype.decode_le(&buf, None, &mut out[o..o + row]);
            }
        }
        Ok(())
    }
}

/// A grid held in memory (horizons, tests).
pub struct MemorySource {
    /// Samples per axis.
    pub dims: [u64; 3],
    /// Samples, x fastest.
    pub data: Vec<f32>,
}

impl GridSource for MemorySource {
    fn dims(&self) -> [u64; 3] {
        self.dims
    }
    fn contiguous_axis(&self) -> usize {
        0
    }
    fn read_box(&self, lo: [u64; 3], size: [u64; 3], out: &mut [f32]) -> Result<()> {
        let row = size[0] as usize;
        for z in 0..size[2] {
            for y in 0..size[1] {
                let s = (((lo[2] + z) * self.dims[1] + lo[1] + y) * self.dims[0] + lo[0]) as usize;
                let o = ((z * size[1] + y) as usize) * row;
                out[o..o + row].copy_from_slice(&self.data[s..s + row]);
            }
        }
        Ok(())
    }
}
