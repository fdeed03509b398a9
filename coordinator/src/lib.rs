//! # strata-coordinator
//!
//! The user-facing side of Strata: ingest of real formats into page stores, synthetic
//! seismic surveys, inspection, and (later) the distributed render driver.
//!
//! * [`source`]: the `GridSource` trait the builder reads through, raw files, memory grids.
//! * [`builder`]: streams a source into a page store with bounded memory.
//! * [`segy`]: SEG-Y rev 0/1/2 reading (and writing, for synthetic tests).
//! * [`horizon_text`]: interpreted horizons from text exports.
//! * [`synth`]: deterministic synthetic seismic surveys.
//! * [`inspect`]: store summaries, verification and digests.
//! * [`overrides`]: loading a scene with `--set KEY=VALUE` and `--size WxH` overrides.
//! * [`decompose`]: the cost-balanced k-d split of a scene over workers.
//! * [`demo`]: the scene's built-in synthetic survey, generated once into a cache folder.
//! * [`image_out`]: PNG (sRGB, flattened) and OpenEXR (float RGBA) image writers.
//! * [`study`]: `study accuracy`, error against time for every accuracy knob of a scene.

pub mod builder;
pub mod cluster;
pub mod decompose;
pub mod demo;
pub mod horizon_text;
pub use strata_worker::image_out;
pub mod inspect;
pub mod overrides;
pub mod render;
pub mod segy;
pub mod sequence;
pub mod source;
pub mod study;
pub mod synth;
