//! # strata-net
//!
//! The thin transport under Strata's cluster protocol (whose messages and frame layout
//! live, I/O-free, in `strata_common::wire`):
//!
//! * [`tls`]: a fresh self-signed certificate per process and run, and a client
//!   verifier that accepts exactly one pinned SHA-256 fingerprint (no CA, no names).
//! * [`transport`]: quinn endpoint and transport settings (idle timeout, keep-alive,
//!   flow-control windows, MTU).
//! * [`frame`]: reading and writing length-checked frames on QUIC streams, with a
//!   timeout on every wait.
//! * [`secret`]: the run's shared secret (file or environment), random tokens and a
//!   constant-time comparison.
//! * [`shm`]: shared-memory segments between processes on one host (sealed anonymous
//!   memory files mapped by both sides), announced over the authenticated connection.
//! * [`canvas`]: the coordinator's frame-sized shared image that the workers on its host
//!   write their final spans into.

#![deny(missing_docs)]

pub mod canvas;
pub mod frame;
pub mod secret;
pub mod shm;
pub mod tls;
pub mod transport;

pub use frame::{
    read_frame, send_uni, send_uni_chunks, with_timeout, write_frame, write_frame_chunks, Frame,
    NetError,
};
pub use tls::Identity;
pub use transport::NetConfig;

/// Microseconds since the Unix epoch: comparable between processes on one machine (the
/// coordinator times compositing from the workers' render-end stamps to the last piece).
pub fn unix_us() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}
