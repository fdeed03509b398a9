//! Endpoint and transport settings.

use crate::tls::{self, Identity};
use anyhow::{Context, Result};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use strata_common::wire::Fingerprint;

/// Transport knobs (from the scene's `[cluster]` section).
#[derive(Clone, Debug)]
pub struct NetConfig {
    /// A connection that hears nothing for this long is closed (a vanished peer).
    pub idle_timeout: Duration,
    /// Keep-alive pings, so a quiet but healthy connection never idles out.
    pub keep_alive: Duration,
    /// First UDP payload size. 1200 is safe on any path; loopback and jumbo-frame
    /// networks can start higher (path MTU discovery raises it anyway).
    pub initial_mtu: u16,
}

impl Default for NetConfig {
    fn default() -> Self {
        NetConfig {
            idle_timeout: Duration::from_secs(10),
            keep_alive: Duration::from_secs(2),
            initial_mtu: 1200,
        }
    }
}

impl NetConfig {
    /// The quinn transport configuration.
    pub fn transport(&self) -> Result<Arc<quinn::TransportConfig>> {
        let mut t = quinn::TransportConfig::default();
        t.max_idle_timeout(Some(
            quinn::IdleTimeout::try_from(self.idle_timeout).context("idle timeout too large")?,
        ));
        t.keep_alive_interval(Some(self.keep_alive.min(self.idle_timeout / 2)));
        // Image pieces are tens of MB; windows of a few tens of MB keep a loopback or LAN
        // link busy without letting one peer pin unbounded memory.
        t.stream_receive_window(quinn::VarInt::from_u32(32 << 20));
        t.receive_window(quinn::VarInt::from_u32(128 << 20));
        t.send_window(128 << 20);
        t.max_concurrent_uni_streams(quinn::VarInt::from_u32(1024));
        t.max_concurrent_bidi_streams(quinn::VarInt::from_u32(16));
        t.initial_mtu(self.initial_mtu.max(1200));
        Ok(Arc::new(t))
    }
}

/// An endpoint bound to `bind` that accepts connections with `id` (and can open them).
pub fn endpoint(bind: SocketAddr, id: &Identity, cfg: &NetConfig) -> Result<quinn::Endpoint> {
    let server = tls::server_config(id, cfg.transport()?)?;
    quinn::Endpoint::server(server, bind).with_context(|| format!("cannot bind UDP {bind}"))
}

/// Connects to `addr`, accepting only the certificate with fingerprint `pinned`, within
/// `timeout`.
pub async fn connect(
    ep: &quinn::Endpoint,
    addr: SocketAddr,
    pinned: Fingerprint,
    cfg: &NetConfig,
    timeout: Duration,
) -> Result<quinn::Connection> {
    let client = tls::client_config(pinned, cfg.transport()?)?;
    let connecting = ep
        .connect_with(client, addr, tls::SERVER_NAME)
        .with_context(|| format!("cannot connect to {addr}"))?;
    match tokio::time::timeout(timeout, connecting).await {
        Ok(Ok(c)) => Ok(c),
        Ok(Err(e)) => Err(anyhow::anyhow!("connecting to {addr}: {e}")),
        Err(_) => Err(anyhow::anyhow!(
            "connecting to {addr}: no answer within {:.1} s",
            timeout.as_secs_f64()
        )),
    }
}
