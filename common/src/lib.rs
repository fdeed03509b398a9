//! # strata-common
//!
//! The I/O-free core of Strata, shared by the coordinator and the workers:
//!
//! * [`ids`]: unified page ids (data set, level, Morton index) and Morton codes.
//! * [`pyramid`]: the level/brick arithmetic of the multi-resolution page trees
//!   (octrees of bricks for volumes, quadtrees of tiles for horizons).
//! * [`sample`]: on-disk sample types and their exact conversion to `f32`.
//! * [`filter`]: the coarsening filters that build level `l+1` from level `l`.
//! * [`store`]: the page-store file format (header, Z-order index, page codec)
//!   and its reader. The reader is the one place in this crate that touches a
//!   file, and only through positional reads (`pread`), so any number of
//!   threads can fetch pages at once without locking.
//! * [`digest`]: an order-independent digest of a data set's level-0 samples,
//!   so two stores with the same data print the same digest whatever their
//!   brick size, compression or source byte order.
//! * [`effects`]: the effect sets the casters' code is specialised to, and a frame's variant
//!   (its effects and the effects its code path has compiled in).
//! * [`geo`]: f64 affine transforms (and their inverses) and the lateral survey grid.
//! * [`camera`]: the view: f64 camera and data transforms, camera-relative f32 rays, the
//!   default camera that frames a scene, and orbits around it.
//! * [`camera_path`]: keyframed camera paths for frame sequences (linear or smooth).
//! * [`tf`]: colour maps and transfer functions (opacity-corrected step tables, page
//!   transparency for empty-space skipping).
//! * [`gpu`]: the `#[repr(C)]` tables both ray-casting backends read (page-table entries,
//!   level and slot records, per-frame, per-volume and per-horizon parameters, the volume
//!   pool's element format), with size assertions.
//! * [`image`]: premultiplied RGBA partial images and the OVER operator.
//! * [`composite`]: the sans-IO sort-last compositing plans (direct send, binary swap,
//!   radix-k, gather), active-pixel encoding and the rank state machine that runs a plan.
//! * [`wire`]: the cluster protocol: frame header, limits and messages (no I/O).
//! * [`kd`]: half-open regions, k-d trees and their visibility order.
//! * [`occlusion`]: per-block transmittance of partial images and the blocks each position
//!   of the visibility order may leave uncast (cross-worker occlusion).
//! * [`scene`]: the scene description (TOML) with errors that name line and column.
//! * [`temp_name`]: the hidden name an output is written under before its rename.
//!
//! No async, no networking, no threads are spawned here.
#![deny(missing_docs)]

pub mod camera;
pub mod camera_path;
pub mod composite;
pub mod digest;
pub mod effects;
pub mod filter;
pub mod geo;
pub mod gpu;
pub mod ids;
pub mod image;
pub mod kd;
pub mod occlusion;
pub mod pyramid;
pub mod sample;
pub mod scene;
pub mod stats;
pub mod store;
pub mod temp_name;
pub mod tf;
pub mod wall;
pub mod wire;
