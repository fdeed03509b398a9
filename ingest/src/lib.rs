//! # strata-ingest
//!
//! Everything that turns third-party files into Strata page stores, in one place:
//!
//! * [`source`]: the `GridSource` trait the builder reads through, raw files, memory grids.
//! * [`builder`]: streams a source into a page store with bounded memory.
//! * [`cleanup`]: its temporary file unlinked when a signal ends the process.
//! * [`segy`]: SEG-Y rev 0/1/2 reading (and writing, for synthetic tests).
//! * [`horizon_text`]: interpreted horizons from text exports.
//! * [`synth`]: deterministic synthetic seismic surveys.
//! * [`inspect`]: store summaries, verification and digests.
//!
//! The coordinator's `ingest`, `synth` and `inspect` commands are thin wrappers over these.

#![deny(missing_docs)]

pub mod builder;
pub mod cleanup;
pub mod horizon_text;
pub mod inspect;
pub mod segy;
pub mod source;
pub mod synth;
