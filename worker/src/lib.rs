//! # strata-worker
//!
//! The worker engine: given a region of space (a half-open box of the k-d split), a camera
//! and the scene, it produces the premultiplied RGBA partial image of everything inside the
//! region, streaming its data out of core and refining the level of detail by feedback from
//! the rays.
//!
//! * [`cache`]: the host page cache (byte budget, LRU, locked pages, loader threads with a
//!   priority queue in which real requests outrank prefetch).
//! * [`atlas`]: the virtualized atlas: fixed pools of page slots and per-data-set page
//!   tables, in the `#[repr(C)]` layout of `strata_common::gpu` that both backends read.
//! * [`feedback`]: per-ray page requests, reduced to priorities.
//! * [`camera`]: f64 camera and data transforms, camera-relative f32 rays.
//! * [`tf`]: colour maps and transfer functions (opacity-corrected step tables).
//! * [`volume`], [`horizon`], [`raycast`]: the CPU ray caster.
//! * [`gpu`]: the wgpu backend: atlas pool and page tables in GPU buffers, the WGSL caster
//!   of volumes, feedback counted and compacted on the GPU (`render.backend`).
//! * [`engine`]: frames, feedback → loads → atlas updates, batch convergence.
#![deny(missing_docs)]

pub mod atlas;
pub mod cache;
pub mod camera;
pub mod cli;
pub mod dataset;
pub mod engine;
pub mod feedback;
pub mod gpu;
pub mod horizon;
pub mod node;
pub mod raycast;
pub mod tf;
pub mod volume;
