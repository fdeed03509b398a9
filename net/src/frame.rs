//! Frames on QUIC streams: header first, limits checked, then the body.

use std::future::Future;
use std::time::Duration;
use strata_common::wire::{self, Limits, WireError, HEADER_LEN};

/// A received frame.
#[derive(Debug, Default)]
pub struct Frame {
    /// The bincode meta message.
    pub meta: Vec<u8>,
    /// The raw bulk payload (may be empty).
    pub bulk: Vec<u8>,
}

impl Frame {
    /// Bytes this frame took on the wire.
    pub fn wire_len(&self) -> u64 {
        (HEADER_LEN + self.meta.len() + self.bulk.len()) as u64
    }
}

/// Transport failures.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    /// A wait ran out.
    #[error("{what}: nothing within {secs:.1} s")]
    Timeout {
        /// What was awaited.
        what: String,
        /// The timeout.
        secs: f64,
    },
    /// The stream ended where a frame was expected.
    #[error("stream finished early: {0}")]
    Truncated(String),
    /// The connection is gone.
    #[error("connection lost: {0}")]
    Connection(#[from] quinn::ConnectionError),
    /// A stream error.
    #[error("stream error: {0}")]
    Stream(String),
    /// The peer sent something that is not a valid frame.
    #[error("{0}")]
    Wire(#[from] WireError),
}

/// Awaits `fut` for at most `timeout`.
pub async fn with_timeout<T, E>(
    timeout: Duration,
    what: impl Into<String>,
    fut: impl Future<Output = Result<T, E>>,
) -> Result<T, NetError>
where
    NetError: From<E>,
{
    match tokio::time::timeout(timeout, fut).await {
        Ok(r) => r.map_err(NetError::from),
        Err(_) => Err(NetError::Timeout {
            what: what.into(),
            secs: timeout.as_secs_f64(),
        }),
    }
}

impl From<quinn::ReadExactError> for NetError {
    fn from(e: quinn::ReadExactError) -> Self {
        match e {
            quinn::ReadExactError::FinishedEarly(n) => {
                NetError::Truncated(format!("after {n} more bytes"))
            }
            quinn::ReadExactError::ReadError(e) => read_error(e),
        }
    }
}

impl From<quinn::WriteError> for NetError {
    fn from(e: quinn::WriteError) -> Self {
        match e {
            quinn::WriteError::ConnectionLost(c) => NetError::Connection(c),
            e => NetError::Stream(e.to_string()),
        }
    }
}

impl From<quinn::ClosedStream> for NetError {
    fn from(e: quinn::ClosedStream) -> Self {
        NetError::Stream(e.to_string())
    }
}

fn read_error(e: quinn::ReadError) -> NetError {
    match e {
        quinn::ReadError::ConnectionLost(c) => NetError::Connection(c),
        e => NetError::Stream(e.to_string()),
    }
}

/// Writes one frame. The stream is not finished, so a control stream can carry more.
pub async fn write_frame(
    send: &mut quinn::SendStream,
    meta: &[u8],
    bulk: &[u8],
) -> Result<u64, NetError> {
    let header = wire::encode_header(meta.len() as u32, bulk.len() as u64);
    send.write_all(&header).await?;
    send.write_all(meta).await?;
    if !bulk.is_empty() {
        send.write_all(bulk).await?;
    }
    Ok((HEADER_LEN + meta.len() + bulk.len()) as u64)
}

/// [`write_frame`] of a bulk payload in chunks that are sent as they are: quinn keeps
/// each chunk instead of copying it into its send buffer.
pub async fn write_frame_chunks(
    send: &mut quinn::SendStream,
    meta: &[u8],
    mut bulk: Vec<bytes::Bytes>,
) -> Result<u64, NetError> {
    let bulk_len: usize = bulk.iter().map(|b| b.len()).sum();
    let header = wire::encode_header(meta.len() as u32, bulk_len as u64);
    send.write_all(&header).await?;
    send.write_all(meta).await?;
    send.write_all_chunks(&mut bulk).await?;
    Ok((HEADER_LEN + meta.len() + bulk_len) as u64)
}

/// Reads one frame, refusing it by its header before allocating the body.
pub async fn read_frame(recv: &mut quinn::RecvStream, limits: &Limits) -> Result<Frame, NetError> {
    let mut header = [0u8; HEADER_LEN];
    recv.read_exact(&mut header).await?;
    let h = wire::decode_header(&header, limits)?;
    let mut meta = vec![0u8; h.meta_len as usize];
    recv.read_exact(&mut meta).await?;
    let bulk = read_exactly(recv, h.bulk_len as usize).await?;
    Ok(Frame { meta, bulk })
}

/// Reads `len` bytes without zero-filling a buffer first (pieces are tens of MB).
async fn read_exactly(recv: &mut quinn::RecvStream, len: usize) -> Result<Vec<u8>, NetError> {
    // Reserve by what has arrived, not by what the header promises (capped at 64 MiB up
    // front), so a lying header costs at most that much.
    let mut out = Vec::with_capacity(len.min(64 << 20));
    while out.len() < len {
        match recv
            .read_chunk(len - out.len(), true)
            .await
            .map_err(read_error)?
        {
            Some(chunk) => out.extend_from_slice(&chunk.bytes),
            None => {
                return Err(NetError::Truncated(format!(
                    "after {} of {len} payload bytes",
                    out.len()
                )))
            }
        }
    }
    Ok(out)
}

/// [`send_uni`] with the bulk in chunks sent as they are ([`write_frame_chunks`]).
pub async fn send_uni_chunks(
    conn: &quinn::Connection,
    meta: &[u8],
    bulk: Vec<bytes::Bytes>,
) -> Result<u64, NetError> {
    let mut s = conn.open_uni().await?;
    let n = write_frame_chunks(&mut s, meta, bulk).await?;
    s.finish()?;
    Ok(n)
}

/// Sends one frame on a new unidirectional stream and finishes it.
pub async fn send_uni(conn: &quinn::Connection, meta: &[u8], bulk: &[u8]) -> Result<u64, NetError> {
    let mut s = conn.open_uni().await?;
    let n = write_frame(&mut s, meta, bulk).await?;
    s.finish()?;
    Ok(n)
}
