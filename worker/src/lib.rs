//! # strata-worker
//!
//! The worker engine: given a region of space (a half-open box of the k-d split), a camera
//! and the scene, it produces the premultiplied RGBA partial image of everything inside the
//! region, streaming its data out of core and refining the level of detail by feedback from
//! the rays.
//!
//! * [`affinity`]: the CPUs a process may run on; binding local workers to their own.
//! * [`cache`]: the host page cache (byte budget, LRU, locked pages, loader threads with a
//!   priority queue in which real requests outrank prefetch).
//! * [`atlas`]: the virtualized atlas: fixed pools of page slots and per-data-set page
//!   tables, in the `#[repr(C)]` layout of `strata_common::gpu` that both backends read.
//! * [`feedback`]: per-ray page requests, reduced to priorities.
//! * [`volume`], [`horizon`], [`raycast`]: the CPU ray caster; [`macrocell`]: its
//!   empty-space skipping inside bricks; [`packet`]: its SIMD ray packets (AVX2 or AVX-512).
//! * [`gpu`]: the wgpu backend: atlas pools and page tables in GPU buffers, the WGSL caster
//!   of volumes and horizons, feedback counted and compacted on the GPU (`render.backend`).
//!
//! The maths both backends and the coordinator use (the camera and view, transfer
//! functions and colour maps, page transparency, affine inverses) lives in
//! `strata_common` (`camera`, `tf`, `geo`).
//! * [`engine`]: frames, feedback → loads → atlas updates, batch convergence.
//! * [`dataset`]: open stores with their transforms and per-page value bounds.
//! * [`node`]: the worker as a cluster node (coordinator link, peer mesh, the compositing
//!   exchange per frame); [`peer_budget`]: the bytes of pieces queued between its peer
//!   readers and its frame loop; [`canvas_cache`]: the coordinator's canvases it keeps mapped;
//!   [`cli`]: its `--connect` command line.
//! * [`image_out`]: PNG (sRGB, flattened) and OpenEXR (float RGBA) writers, atomic; a
//!   wall's tile files and its preview mosaic.
#![deny(missing_docs)]

pub mod affinity;
pub mod atlas;
pub mod cache;
pub mod canvas_cache;
pub mod cli;
pub mod dataset;
pub mod engine;
pub mod feedback;
pub mod gpu;
pub mod horizon;
pub mod image_out;
pub mod macrocell;
pub mod node;
pub mod packet;
pub mod peer_budget;
pub mod raycast;
pub mod volume;
