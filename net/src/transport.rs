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
    /// Demand a certificate from every client (workers' endpoints: peers pin each other).
    pub client_auth: bool,
    /// Generic segmentation offload: one system call sends a train of datagrams where the
    /// OS has it (Linux); quinn falls back by itself where it has not. On by default; off
    /// only to measure what it gives (`bench-composite` does).
    pub segmentation_offload: bool,
}

impl Default for NetConfig {
    fn default() -> Self {
        NetConfig {
            idle_timeout: Duration::from_secs(10),
            keep_alive: Duration::from_secs(2),
            initial_mtu: 1200,
            client_auth: false,
            segmentation_offload: true,
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
        // Until a peer has proven itself (`trust`), it may open one stream of each kind
        // and have at most PRE_AUTH_WINDOW bytes buffered.
        t.stream_receive_window(quinn::VarInt::from_u32(32 << 20));
        t.receive_window(quinn::VarInt::from_u32(PRE_AUTH_WINDOW));
        t.send_window(128 << 20);
        t.max_concurrent_uni_streams(quinn::VarInt::from_u32(1));
        t.max_concurrent_bidi_streams(quinn::VarInt::from_u32(1));
        // Strata sends no unreliable datagrams; unsupported, a peer's DATAGRAM frame is a
        // protocol violation instead of up to 1.25 MB (quinn's default) queued per
        // connection, past the window above, before any proof of who it is.
        t.datagram_receive_buffer_size(None);
        t.initial_mtu(self.initial_mtu.max(1200));
        t.enable_segmentation_offload(self.segmentation_offload);
        if self.initial_mtu > 1452 {
            // Let path MTU discovery keep (and probe above) a large starting size instead
            // of capping it at the Ethernet-safe 1452.
            let mut m = quinn::MtuDiscoveryConfig::default();
            m.upper_bound(self.initial_mtu);
            t.mtu_discovery_config(Some(m));
        }
        Ok(Arc::new(t))
    }
}

/// Connection-level receive window before authentication.
pub const PRE_AUTH_WINDOW: u32 = 256 << 10;

/// Opens the flow-control windows of a connection whose peer has been authenticated
/// (secret, run token, or a pinned certificate we dialled): image pieces are tens of MB,
/// and windows of that size keep a loopback or LAN link busy.
pub fn trust(conn: &quinn::Connection) {
    conn.set_receive_window(quinn::VarInt::from_u32(128 << 20));
    conn.set_max_concurrent_uni_streams(quinn::VarInt::from_u32(1024));
    conn.set_max_concurrent_bi_streams(quinn::VarInt::from_u32(4));
}

/// Bytes asked for each UDP socket's receive and send buffer. A piece of tens of MB
/// arrives as a burst of datagrams faster than one task drains them; the default buffer
/// (about 208 KiB on Linux) overflows, every dropped datagram is a loss to the congestion
/// controller, and the stream crawls. The kernel caps the request at
/// `net.core.rmem_max` / `wmem_max` (raise those for fast links).
pub const SOCKET_BUFFER: usize = 16 << 20;

/// Asks for `bytes` of receive and send buffer on `socket` and returns what the kernel
/// granted (it caps the request at its limit, and reports twice the usable size).
pub fn size_socket_buffers(socket: &std::net::UdpSocket, bytes: usize) -> (usize, usize) {
    use std::os::fd::AsRawFd;
    let fd = socket.as_raw_fd();
    let want = bytes.min(i32::MAX as usize) as libc::c_int;
    let mut got = [0usize; 2];
    for (i, opt) in [libc::SO_RCVBUF, libc::SO_SNDBUF].into_iter().enumerate() {
        // SAFETY: setsockopt/getsockopt on a socket we own, with an int-sized option
        // value; failures leave the default, which works, only slower.
        unsafe {
            libc::setsockopt(
                fd,
                libc::SOL_SOCKET,
                opt,
                (&want as *const libc::c_int).cast(),
                std::mem::size_of::<libc::c_int>() as libc::socklen_t,
            );
            let mut v: libc::c_int = 0;
            let mut len = std::mem::size_of::<libc::c_int>() as libc::socklen_t;
            if libc::getsockopt(
                fd,
                libc::SOL_SOCKET,
                opt,
                (&mut v as *mut libc::c_int).cast(),
                &mut len,
            ) == 0
            {
                got[i] = v.max(0) as usize;
            }
        }
    }
    (got[0], got[1])
}

/// An endpoint bound to `bind` that accepts connections with `id` (and can open them).
pub fn endpoint(bind: SocketAddr, id: &Identity, cfg: &NetConfig) -> Result<quinn::Endpoint> {
    let server = tls::server_config(id, cfg.transport()?, cfg.client_auth)?;
    // Accept datagrams as large as any peer's MTU (quinn's default drops anything above
    // 1472 bytes, which would silently black-hole a peer configured for loopback sizes).
    let mut ec = quinn::EndpointConfig::default();
    ec.max_udp_payload_size(65527)
        .map_err(|e| anyhow::anyhow!("max UDP payload: {e:?}"))?;
    let socket =
        std::net::UdpSocket::bind(bind).with_context(|| format!("cannot bind UDP {bind}"))?;
    let (rcv, snd) = size_socket_buffers(&socket, SOCKET_BUFFER);
    tracing::debug!(%bind, receive_buffer = rcv, send_buffer = snd, "UDP socket buffers");
    quinn::Endpoint::new(ec, Some(server), socket, Arc::new(quinn::TokioRuntime))
        .with_context(|| format!("cannot start a QUIC endpoint on {bind}"))
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
    connect_as(ep, addr, pinned, None, cfg, timeout).await
}

/// [`connect`], presenting `id`'s certificate to a server that demands one (a peer
/// worker, which checks it against the rank this side claims).
pub async fn connect_as(
    ep: &quinn::Endpoint,
    addr: SocketAddr,
    pinned: Fingerprint,
    id: Option<&Identity>,
    cfg: &NetConfig,
    timeout: Duration,
) -> Result<quinn::Connection> {
    match attempt(ep, addr, pinned, id, cfg, timeout).await {
        Ok(c) => Ok(c),
        Err(Attempt::Quic(e)) => Err(anyhow::anyhow!("connecting to {addr}: {e}")),
        Err(Attempt::NoAnswer) => Err(anyhow::anyhow!(
            "connecting to {addr}: no answer within {:.1} s",
            timeout.as_secs_f64()
        )),
        Err(Attempt::Setup(e)) => Err(e),
    }
}

/// How one connection attempt failed.
enum Attempt {
    /// The QUIC handshake failed.
    Quic(quinn::ConnectionError),
    /// Nothing within the time given.
    NoAnswer,
    /// The attempt could not be made (client configuration, address).
    Setup(anyhow::Error),
}

async fn attempt(
    ep: &quinn::Endpoint,
    addr: SocketAddr,
    pinned: Fingerprint,
    id: Option<&Identity>,
    cfg: &NetConfig,
    timeout: Duration,
) -> Result<quinn::Connection, Attempt> {
    let setup = || -> Result<quinn::Connecting> {
        let client = tls::client_config(pinned, cfg.transport()?, id)?;
        ep.connect_with(client, addr, tls::SERVER_NAME)
            .with_context(|| format!("cannot connect to {addr}"))
    };
    let connecting = setup().map_err(Attempt::Setup)?;
    match tokio::time::timeout(timeout, connecting).await {
        Ok(Ok(c)) => Ok(c),
        Ok(Err(e)) => Err(Attempt::Quic(e)),
        Err(_) => Err(Attempt::NoAnswer),
    }
}

/// [`connect_as`], tried again until `timeout` while the peer is not there yet or turns the
/// attempt away: a worker started before its coordinator listens, or while the
/// coordinator's queue of unauthenticated connections is full, keeps trying for its whole
/// `--connect-timeout-s`. One attempt gives up after `cfg.idle_timeout` without an answer
/// (QUIC's handshake idles out), which alone would cut the time short. An attempt that
/// fails otherwise (a certificate that is not the pinned one, a closed connection) ends
/// the wait at once. Pauses between attempts grow from 100 ms to 2 s.
pub async fn connect_until(
    ep: &quinn::Endpoint,
    addr: SocketAddr,
    pinned: Fingerprint,
    id: Option<&Identity>,
    cfg: &NetConfig,
    timeout: Duration,
) -> Result<quinn::Connection> {
    let deadline = tokio::time::Instant::now() + timeout;
    let mut pause = Duration::from_millis(100);
    let mut attempts = 0u32;
    loop {
        attempts += 1;
        let left = deadline.saturating_duration_since(tokio::time::Instant::now());
        let e = match attempt(ep, addr, pinned, id, cfg, left).await {
            Ok(c) => return Ok(c),
            Err(Attempt::NoAnswer) => break,
            Err(Attempt::Setup(e)) => return Err(e),
            Err(Attempt::Quic(e)) => e,
        };
        let again = match &e {
            quinn::ConnectionError::TimedOut | quinn::ConnectionError::Reset => true,
            quinn::ConnectionError::ConnectionClosed(c) => {
                c.error_code == quinn::TransportErrorCode::CONNECTION_REFUSED
            }
            _ => false,
        };
        if !again {
            anyhow::bail!("connecting to {addr}: {e}");
        }
        if tokio::time::Instant::now() + pause >= deadline {
            break;
        }
        tracing::debug!(%addr, attempts, error = %e, "no connection yet; trying again");
        tokio::time::sleep(pause).await;
        pause = (pause * 2).min(Duration::from_secs(2));
    }
    anyhow::bail!(
        "connecting to {addr}: no answer within {:.1} s ({attempts} attempts)",
        timeout.as_secs_f64()
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A worker that starts before its coordinator listens keeps trying: the server comes
    /// up after several of the client's attempts have idled out, and the connection is
    /// made. A server with another certificate ends the wait at once.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn connect_until_waits_for_a_late_server_and_not_for_a_wrong_one() {
        let cfg = NetConfig {
            idle_timeout: Duration::from_millis(300),
            ..NetConfig::default()
        };
        let server_id = tls::Identity::generate().unwrap();
        // A free port: bound, then closed, and taken again later by the server.
        let port = std::net::UdpSocket::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let addr: SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
        let (id, sc) = (server_id.fingerprint, cfg.clone());
        let server = tokio::spawn(async move {
            tokio::time::sleep(Duration::from_millis(1500)).await;
            let server = endpoint(addr, &server_id, &sc).unwrap();
            let incoming = server.accept().await.expect("a connection");
            let conn = incoming.await.expect("a handshake");
            (server, conn)
        });
        let client_id = tls::Identity::generate().unwrap();
        let client = endpoint("127.0.0.1:0".parse().unwrap(), &client_id, &cfg).unwrap();
        let t = std::time::Instant::now();
        let conn = connect_until(&client, addr, id, None, &cfg, Duration::from_secs(20))
            .await
            .expect("connected once the server listened");
        assert!(
            t.elapsed() >= Duration::from_millis(1400),
            "{:?}",
            t.elapsed()
        );
        let (server, _sconn) = server.await.unwrap();
        drop(conn);
        // The wrong certificate: refused at the first attempt, long before the timeout.
        let other = tls::Identity::generate().unwrap().fingerprint;
        let accept = tokio::spawn(async move {
            if let Some(i) = server.accept().await {
                let _ = i.await;
            }
            server
        });
        let t = std::time::Instant::now();
        let e = connect_until(&client, addr, other, None, &cfg, Duration::from_secs(20))
            .await
            .unwrap_err();
        assert!(
            t.elapsed() < Duration::from_secs(5),
            "{:?}: {e:#}",
            t.elapsed()
        );
        // And nobody there at all: the whole timeout, then an error that says so.
        let t = std::time::Instant::now();
        let e = connect_until(
            &client,
            "127.0.0.1:9".parse().unwrap(),
            id,
            None,
            &cfg,
            Duration::from_millis(1200),
        )
        .await
        .unwrap_err();
        assert!(
            t.elapsed() >= Duration::from_millis(1000),
            "{:?}",
            t.elapsed()
        );
        assert!(e.to_string().contains("no answer within 1.2 s"), "{e:#}");
        drop(accept);
    }

    /// Connections offer no DATAGRAM support, either way: a stranger cannot queue datagrams
    /// before it has proven who it is.
    #[tokio::test(flavor = "multi_thread", worker_threads = 1)]
    async fn connections_take_no_datagrams() {
        let cfg = NetConfig::default();
        let server_id = tls::Identity::generate().unwrap();
        let server = endpoint("127.0.0.1:0".parse().unwrap(), &server_id, &cfg).unwrap();
        let addr = server.local_addr().unwrap();
        let accept = tokio::spawn(async move {
            let incoming = server.accept().await.expect("a connection");
            let conn = incoming.await.expect("a handshake");
            let offered = conn.max_datagram_size();
            (server, conn, offered)
        });
        let client_id = tls::Identity::generate().unwrap();
        let client = endpoint("127.0.0.1:0".parse().unwrap(), &client_id, &cfg).unwrap();
        let conn = connect_as(
            &client,
            addr,
            server_id.fingerprint,
            Some(&client_id),
            &cfg,
            Duration::from_secs(10),
        )
        .await
        .unwrap();
        let (_server, _sconn, offered_by_client) = accept.await.unwrap();
        assert_eq!(
            conn.max_datagram_size(),
            None,
            "the server offers datagrams"
        );
        assert_eq!(offered_by_client, None, "the client offers datagrams");
    }
}
