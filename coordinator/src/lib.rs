//! # strata-coordinator
//!
//! The user-facing side of Strata: the `coordinator` command (ingest, synthetic surveys,
//! inspection, studies) and the distributed render driver that plans, launches and
//! gathers from workers.
//!
//! * [`source`], [`builder`], [`segy`], [`horizon_text`], [`synth`], [`inspect`]: the data
//!   layer's ingest, re-exported from `strata-ingest` (where it lives) under its old paths.
//! * [`overrides`]: loading a scene with `--set KEY=VALUE` and `--size WxH` overrides.
//! * [`decompose`]: the cost-balanced k-d split of a scene over workers.
//! * [`demo`]: the scene's built-in synthetic survey, generated once into a cache folder.
//! * [`image_out`]: PNG (sRGB, flattened) and OpenEXR (float RGBA) image writers.
//! * [`study`]: `study accuracy`, error against time for every accuracy knob of a scene.
//! * [`render`]: `coordinator render`, a scene to images, in process or over workers;
//!   [`cluster`]: the coordinator's side of a distributed render (workers started or
//!   awaited, authenticated, handed their regions; per frame the camera, the visibility
//!   order and the gather); [`setup_blame`]: who is to blame when a set-up fails;
//!   [`sequence`]: the numbered output paths of frame sequences and their MP4.

#![deny(missing_docs)]

pub mod cluster;
pub mod decompose;
pub mod demo;
pub use strata_ingest::{builder, horizon_text, inspect, segy, source, synth};
pub use strata_worker::image_out;
pub mod overrides;
pub mod render;
pub mod sequence;
pub mod setup_blame;
pub mod study;
