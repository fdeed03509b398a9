//! The worker as a cluster node: connect to the coordinator, mesh with the peers, then
//! render and composite frames on request.
//!
//! One QUIC endpoint serves everything: its client side dials the coordinator and the
//! higher-ranked peers, its server side accepts the lower-ranked peers. The coordinator
//! sees the endpoint's address on the worker's connection and hands it to the peers, so
//! no port has to be configured. Peers pin each other's certificates. Pieces to a peer on
//! the same host go through a shared-memory segment (`strata_net::shm`), announced over
//! QUIC; others travel inline on QUIC streams. The exchange itself is the sans-IO
//! `strata_common::composite::Exchange`; this module only moves its pieces and the time.
//! Before the exchange, under cross-worker occlusion, the worker sends the coordinator its
//! image's block transmittance (unless it is last in the visibility order) and receives
//! what lies in front of it (unless it is first), which limits its rays
//! in the next frame (or after a low-resolution first pass) and re-casts the blocks this
//! frame's map does not confirm (`strata_common::occlusion`).
//! Every wait has a deadline; a peer or coordinator that vanishes is detected by the QUIC
//! idle timeout (keep-alives run underneath), or by the coordinator's `PeerLost`, and
//! turns into an error that names it and blames it (`WorkerMsg::Failed::suspects`).

use crate::engine::{Engine, Outcome};
use crate::image_out::write_tiles;
use crate::peer_budget::PieceBudget;
use anyhow::{anyhow, bail, Context, Result};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};
use strata_common::camera::View;
use strata_common::composite::{
    build_plan_to, Exchange, ExchangeError, ExchangeEvent, ExchangeLimits, FinalPiece, FinalTarget,
    Interlace, Outgoing, OutgoingPiece, PieceLayout, PieceSink, Plan, RankCompositor, Segment,
    Span, SparsePiece, WireFormat,
};
use strata_common::image::{composite_front_to_back, PartialImage, Rect, Rgba};
use strata_common::occlusion::{
    encode_levels, BlockGrid, BlockMask, FrontTransmittance, RayLimits, Transmittance, CLEAR,
    MAX_BLOCK,
};
use strata_common::scene::Scene;
use strata_common::wire::{
    self, CompositeChoice, CoordMsg, Fingerprint, FrameRequest, FrameSource, Limits, PageWork,
    PeerInfo, PeerMsg, Setup, WorkerFrameStats, WorkerMsg, MAX_PAGE_WORK,
};
use strata_net::canvas::{self, CanvasWriter};
use strata_net::frame::{
    read_frame, send_uni, send_uni_chunks, with_timeout, write_frame, write_frame_chunks, NetError,
};
use strata_net::shm::{SegmentId, ShmReader, ShmWriter};
use strata_net::{transport, Identity, NetConfig};
use tokio::sync::{mpsc, watch};
use tracing::{debug, info, warn};

/// How a worker finds and proves itself to its coordinator.
#[derive(Clone, Debug)]
pub struct NodeOptions {
    /// Coordinator address.
    pub connect: SocketAddr,
    /// Pinned fingerprint of the coordinator's certificate.
    pub fingerprint: Fingerprint,
    /// Shared secret.
    pub secret: wire::Secret,
    /// Name in logs and errors.
    pub name: String,
    /// Local address of the endpoint (port 0: any).
    pub bind: SocketAddr,
    /// How long to keep trying to reach the coordinator.
    pub connect_timeout: Duration,
    /// Idle timeout of the coordinator connection.
    pub idle_timeout: Duration,
    /// First QUIC datagram size.
    pub quic_mtu: u16,
}

/// Keeps freed image buffers in this process's heap instead of handing them back to the
/// kernel. Every frame allocates and frees pieces of tens of MB; by default glibc maps
/// such blocks fresh and unmaps them on free, so each frame pays a page fault per 4 KiB
/// (measured: 9 ms to fill a fresh 16 MB buffer against 0.5 ms for a reused one, which
/// made the first shared-memory exchange slower than its copies by several times).
/// 32 MiB is glibc's ceiling for the mapping threshold.
pub fn retain_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator tunables; called before the threads start.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
    }
}

/// Runs the node until the coordinator says `Shutdown` (Ok) or the run fails (Err).
pub fn run(opts: NodeOptions) -> Result<()> {
    retain_freed_memory();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    rt.block_on(node(opts))
}

/// Messages from the peer reader tasks.
enum PeerEvent {
    Piece {
        rank: u32,
        frame: u64,
        round: u32,
        from: u32,
        piece: SparsePiece,
        wire_len: u64,
        /// The piece's bytes of the readers' budget, given back once the exchange has it.
        _budget: tokio::sync::OwnedSemaphorePermit,
    },
    Lost {
        rank: u32,
        error: String,
    },
}

async fn node(opts: NodeOptions) -> Result<()> {
    let id = Arc::new(Identity::generate()?);
    // Peers dialling this endpoint must present their certificate (pinned both ways).
    let net = NetConfig {
        idle_timeout: opts.idle_timeout,
        initial_mtu: opts.quic_mtu,
        client_auth: true,
        ..NetConfig::default()
    };
    let ep = transport::endpoint(opts.bind, &id, &net)?;
    // Presenting this worker's certificate, which its hello names.
    let conn = transport::connect_until(
        &ep,
        opts.connect,
        opts.fingerprint,
        Some(&id),
        &net,
        opts.connect_timeout,
    )
    .await
    .context("reaching the coordinator")?;
    // The coordinator proved itself with the pinned certificate.
    transport::trust(&conn);
    let (mut csend, mut crecv) = conn.open_bi().await?;
    let hello = WorkerMsg::Hello {
        secret: opts.secret.clone(),
        name: opts.name.clone(),
        pid: std::process::id(),
        fingerprint: id.fingerprint,
        host: strata_net::shm::host_id(),
    };
    tell(
        &mut csend,
        &hello,
        opts.connect_timeout,
        "introducing this worker to the coordinator",
    )
    .await?;
    let control = Limits {
        max_meta: wire::MAX_META,
        max_bulk: 0,
    };
    // Control messages are read by their own task, so a frame in progress hears at once
    // that the coordinator gave up on a peer, and a mesh in progress that a new set-up
    // replaces it (and a read is never cancelled midway).
    let (ctl_tx, mut ctl_rx) = mpsc::channel::<Result<CoordMsg, String>>(16);
    tokio::spawn(async move {
        loop {
            // No deadline between frames (a user may pause); a vanished coordinator ends
            // the connection through the idle timeout.
            let msg = match read_frame(&mut crecv, &control).await {
                Ok(f) => wire::decode_meta::<CoordMsg>(&f.meta).map_err(|e| e.to_string()),
                Err(e) => Err(format!("lost the coordinator: {e}")),
            };
            let end = msg.is_err();
            if ctl_tx.send(msg).await.is_err() || end {
                return;
            }
        }
    });
    // The first set-up. A `PeerLost` may come first (the coordinator gave up on a worker
    // while it was setting the others up): it concerns a set-up this worker never had.
    let first_deadline = tokio::time::Instant::now() + opts.connect_timeout;
    let mut setup = loop {
        match tokio::time::timeout_at(first_deadline, ctl_rx.recv()).await {
            Ok(Some(Ok(CoordMsg::Setup(s)))) => break *s,
            Ok(Some(Ok(CoordMsg::PeerLost { rank }))) => {
                debug!(rank, "a lost peer before the first set-up: ignored")
            }
            Ok(Some(Ok(CoordMsg::Refused { reason }))) => {
                bail!("the coordinator refused this worker: {reason}")
            }
            Ok(Some(Ok(other))) => {
                bail!("expected the set-up from the coordinator, got {other:?}")
            }
            Ok(Some(Err(e))) => bail!("waiting for the coordinator's set-up: {e}"),
            Ok(None) => bail!("waiting for the coordinator's set-up: lost the coordinator"),
            Err(_) => bail!(
                "waiting for the coordinator's set-up: nothing within {:.1} s",
                opts.connect_timeout.as_secs_f64()
            ),
        }
    };
    let server_config = strata_net::tls::server_config(&id, net.transport()?, net.client_auth)?;
    // A set-up, then frames until shutdown; a new set-up (the coordinator lost a worker
    // before the run was ready) replaces the mesh, whatever state it is in.
    // Reads and cache lookups of the engines of earlier set-ups: the stats count them
    // since this worker first opened the scene, whatever set-ups came between.
    let mut earlier = crate::cache::CacheStats::default();
    'setup: loop {
        let rank = setup.rank;
        info!(rank, name = %opts.name, peers = setup.peers.len(), absent = ?setup.absent, "set up");
        ep.set_server_config(Some(server_config.clone()));
        let meshing = WorkerMsg::Meshing {
            attempt: setup.attempt,
        };
        tell(
            &mut csend,
            &meshing,
            opts.connect_timeout,
            "telling the coordinator it meshes",
        )
        .await?;
        let mut suspects = Vec::new();
        let meshed = tokio::select! {
            r = mesh(&ep, &id, setup.clone(), &net, opts.connect_timeout, &mut suspects) => r,
            s = next_setup(&mut ctl_rx) => {
                setup = s?;
                info!(rank, "a new set-up replaces this one");
                continue 'setup;
            }
            e = conn.closed() => Err(anyhow!("lost the coordinator during set-up: {e}")),
        };
        let (mut node, mut ev_rx) = match meshed {
            Ok((mut node, ev_rx)) => {
                node.earlier = earlier;
                (node, ev_rx)
            }
            Err(e) => {
                // Tell the coordinator why, and whom it blames, so it can give up on a
                // lost peer and set the run up again without it.
                warn!(rank, "set-up failed: {e:#}");
                let msg = WorkerMsg::Failed {
                    frame: None,
                    message: format!("{e:#}"),
                    suspects,
                };
                let _ = tell(
                    &mut csend,
                    &msg,
                    Duration::from_secs(2),
                    "reporting the failed set-up",
                )
                .await;
                match tokio::time::timeout(opts.connect_timeout, next_setup(&mut ctl_rx)).await {
                    Ok(Ok(s)) => {
                        setup = s;
                        continue 'setup;
                    }
                    _ => {
                        let _ = csend.finish();
                        tokio::time::sleep(Duration::from_millis(100)).await;
                        return Err(e);
                    }
                }
            }
        };
        test_fault(rank, 0, "ready");
        if node.setup.shm_gather {
            // The final pieces go to the coordinator through shared memory.
            let w = ShmWriter::create()
                .context("creating the shared-memory segment for the coordinator")?;
            let id = w.id();
            let msg = WorkerMsg::ShmSegment {
                name: id.name,
                pid: id.pid,
                fd: id.fd,
            };
            tell(
                &mut csend,
                &msg,
                opts.connect_timeout,
                "announcing the gather segment",
            )
            .await?;
            node.gather_shm = Some(w);
        }
        tell(
            &mut csend,
            &WorkerMsg::Ready,
            opts.connect_timeout,
            "telling the coordinator it is ready",
        )
        .await?;
        info!(rank, "ready");

        loop {
            let msg = match node.deferred.pop_front() {
                Some(m) => m,
                None => match ctl_rx.recv().await {
                    Some(Ok(m)) => m,
                    Some(Err(e)) => bail!("{e}"),
                    None => bail!("lost the coordinator"),
                },
            };
            match msg {
                CoordMsg::PeerLost { rank: lost } => node.peer_given_up(lost)?,
                CoordMsg::Frame(req) => {
                    let frame = req.frame;
                    let result = tokio::select! {
                        r = node.frame(&req, &mut ev_rx, &mut ctl_rx, &mut csend) => r,
                        e = conn.closed() => bail!("lost the coordinator during frame {frame}: {e}"),
                    };
                    node.reclaim_canvas();
                    match result {
                        Ok((mut stats, piece, (composite_start, cpu_start))) => {
                            test_fault(rank, frame, "gather");
                            let t = Instant::now();
                            // Into the coordinator's canvas when it gave one: in place,
                            // nothing to encode or assemble; else `send_final`.
                            let canvas = req.canvas.as_ref().and_then(|c| {
                                tokio::task::block_in_place(|| node.write_canvas(&req, c, &piece))
                                    .map_err(|e| {
                                        warn!(frame, "final piece not in the canvas: {e:#}")
                                    })
                                    .ok()
                            });
                            let (shm, bulk, lz4, bytes) = match canvas {
                                Some(span) => (
                                    None,
                                    Vec::new(),
                                    false,
                                    span.len() as u64 * canvas::PIXEL_BYTES,
                                ),
                                None => node.send_final(frame, &piece),
                            };
                            stats.gather_s += t.elapsed().as_secs_f64();
                            stats.blended_in_canvas = canvas.is_some() && piece.placed;
                            stats.gather_bytes = bytes;
                            stats.composite_s = composite_start.elapsed().as_secs_f64();
                            stats.cpu_s = process_cpu_s() - cpu_start;
                            let msg = WorkerMsg::FrameDone {
                                frame,
                                stats,
                                shm,
                                lz4,
                                canvas,
                            };
                            with_timeout(
                                node.timeout,
                                format!("sending frame {frame}'s result"),
                                write_frame_chunks(&mut csend, &wire::encode_meta(&msg), bulk),
                            )
                            .await?;
                        }
                        Err(e) => {
                            warn!(frame, "frame failed: {e:#}");
                            let msg = WorkerMsg::Failed {
                                frame: Some(frame),
                                message: format!("{e:#}"),
                                suspects: std::mem::take(&mut node.suspects),
                            };
                            let what = format!("reporting frame {frame}'s failure");
                            tell(&mut csend, &msg, node.timeout, what).await?;
                        }
                    }
                }
                CoordMsg::Shutdown => {
                    // Closed here, not left to the peer readers (which hold the
                    // connections open): the wait for the endpoint to go idle below would
                    // otherwise run its full 2 s, which every multi-worker run paid.
                    node.close_peers(0, b"done");
                    break 'setup;
                }
                // The coordinator lost a worker before the run was ready: mesh again.
                CoordMsg::Setup(s) => {
                    node.close_peers(8, b"new set-up");
                    earlier = node.cache_totals();
                    setup = *s;
                    continue 'setup;
                }
                // The map of a frame this worker already gave up waiting for (its deadline
                // passed as the coordinator sent it).
                CoordMsg::Occlusion { frame, .. } => {
                    debug!(frame, "ignoring an occlusion map that came after its frame")
                }
                other => bail!("unexpected message from the coordinator: {other:?}"),
            }
        }
    }
    info!(rank = setup.rank, "shutting down");
    let _ = csend.finish();
    conn.close(0u32.into(), b"done");
    let _ = tokio::time::timeout(Duration::from_secs(2), ep.wait_idle()).await;
    Ok(())
}

/// Sends `msg` to the coordinator within `deadline`. Every write to the coordinator has
/// one: a coordinator that stops reading (flow control) would otherwise hold this worker
/// for good, keep-alives and all.
async fn tell(
    csend: &mut quinn::SendStream,
    msg: &WorkerMsg,
    deadline: Duration,
    what: impl Into<String>,
) -> Result<(), NetError> {
    with_timeout(
        deadline,
        what,
        write_frame(csend, &wire::encode_meta(msg), &[]),
    )
    .await?;
    Ok(())
}

/// The coordinator's next set-up; other control messages before it (a `PeerLost` for the
/// set-up it replaces) are dropped.
async fn next_setup(ctl_rx: &mut mpsc::Receiver<Result<CoordMsg, String>>) -> Result<Setup> {
    loop {
        match ctl_rx.recv().await {
            Some(Ok(CoordMsg::Setup(s))) => return Ok(*s),
            Some(Ok(CoordMsg::PeerLost { rank })) => {
                debug!(peer = rank, "peer given up on during set-up")
            }
            Some(Ok(CoordMsg::Shutdown)) => bail!("the coordinator ended the run during set-up"),
            Some(Ok(other)) => bail!("expected a set-up from the coordinator, got {other:?}"),
            Some(Err(e)) => bail!("{e}"),
            None => bail!("lost the coordinator"),
        }
    }
}

/// Aborts a task when dropped (a mesh replaced by a new set-up stops its dials and its
/// listener).
struct AbortOnDrop<T = ()>(tokio::task::JoinHandle<T>);

impl<T> Drop for AbortOnDrop<T> {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Checks the set-up, meshes with the peers (all but the absent ones) and opens the
/// scene. On failure, `suspects` holds the peers it could not mesh with.
async fn mesh(
    ep: &quinn::Endpoint,
    id: &Arc<Identity>,
    setup: Setup,
    net: &NetConfig,
    connect_timeout: Duration,
    suspects: &mut Vec<u32>,
) -> Result<(Node, mpsc::Receiver<PeerEvent>)> {
    let rank = setup.rank;
    test_fault(rank, 0, "setup");
    setup.check().map_err(|e| anyhow!(e))?;
    let scene: Scene =
        toml::from_str(&setup.scene_toml).context("the scene sent by the coordinator")?;
    let timeout = Duration::from_millis(setup.timeout_ms.max(1));
    let mesh_timeout = connect_timeout.min(timeout);
    let limits = Limits::for_pixels(setup.max_pixels);

    // Peers: accept the lower ranks (spawned first so nobody waits on us), dial the higher.
    let (token_tx, token_rx) = watch::channel(Some(setup.run_token));
    let (peer_tx, mut peer_rx) = mpsc::unbounded_channel::<(u32, quinn::Connection)>();
    let n = setup.peers.len() as u32;
    let fingerprints: Vec<wire::Fingerprint> = setup.peers.iter().map(|p| p.fingerprint).collect();
    let acceptor = AbortOnDrop(tokio::spawn(accept_peers(
        ep.clone(),
        token_rx,
        peer_tx,
        fingerprints,
    )));
    let present = |r: &u32| !setup.absent.contains(r);
    let mut peers: Vec<Option<quinn::Connection>> = vec![None; n as usize];
    // Dial the higher ranks all at once.
    // One deadline for the whole mesh: dials and the wait for the lower ranks share it.
    let deadline = Instant::now() + mesh_timeout;
    let mut dials = Vec::new();
    for r in (rank + 1..n).filter(present) {
        let p = setup.peers[r as usize].clone();
        let (ep, net, token, id) = (ep.clone(), net.clone(), setup.run_token, id.clone());
        dials.push(AbortOnDrop(tokio::spawn(async move {
            let addr: SocketAddr = p
                .addr
                .parse()
                .with_context(|| format!("peer {r} address {:?}", p.addr))?;
            // Until the peer welcomes this set-up's token (or the mesh's deadline): one
            // still meshing for an earlier set-up refuses it, and takes the new one a
            // moment later.
            loop {
                let left = deadline.saturating_duration_since(Instant::now());
                let attempt = async {
                    let c = transport::connect_as(&ep, addr, p.fingerprint, Some(&id), &net, left)
                        .await
                        .with_context(|| {
                            format!("connecting to worker {r} ({} at {})", p.name, p.addr)
                        })?;
                    transport::trust(&c);
                    let hello = PeerMsg::Hello { token, rank };
                    let hello = wire::encode_meta(&hello);
                    with_timeout(left, "peer hello", send_uni(&c, &hello, &[]))
                        .await
                        .with_context(|| format!("greeting worker {r} ({})", p.name))?;
                    let welcome = async {
                        let mut s = c.accept_uni().await?;
                        let f = read_frame(&mut s, &Limits::HANDSHAKE).await?;
                        Ok::<_, NetError>(wire::decode_meta::<PeerMsg>(&f.meta)?)
                    };
                    match with_timeout(left, "peer welcome", welcome).await {
                        Ok(PeerMsg::Welcome) => anyhow::Ok(c),
                        Ok(other) => {
                            bail!("worker {r} ({}) answered {other:?}, not a welcome", p.name)
                        }
                        Err(e) => bail!("worker {r} ({}) did not welcome this worker: {e}", p.name),
                    }
                };
                match attempt.await {
                    Ok(c) => return anyhow::Ok((r, c)),
                    Err(e) if Instant::now() + Duration::from_millis(50) >= deadline => {
                        return Err(e)
                    }
                    Err(e) => {
                        debug!(peer = r, "retrying the mesh: {e:#}");
                        tokio::time::sleep(Duration::from_millis(50)).await;
                    }
                }
            }
        })));
    }
    let mut dial_errors = Vec::new();
    for (r, mut d) in (rank + 1..n).filter(present).zip(dials) {
        match (&mut d.0)
            .await
            .map_err(|e| anyhow!("dial task: {e}"))
            .and_then(|r| r)
        {
            Ok((r, c)) => peers[r as usize] = Some(c),
            Err(e) => {
                suspects.push(r);
                dial_errors.push(format!("{e:#}"));
            }
        }
    }
    if !dial_errors.is_empty() {
        bail!("{}", dial_errors.join("; "));
    }

    let awaited = |peers: &[Option<quinn::Connection>]| -> Vec<u32> {
        (0..rank)
            .filter(|r| present(r) && peers[*r as usize].is_none())
            .collect()
    };
    while !awaited(&peers).is_empty() {
        let left = deadline.saturating_duration_since(Instant::now());
        match tokio::time::timeout(left, peer_rx.recv()).await {
            Ok(Some((r, c))) if r < rank && present(&r) && peers[r as usize].is_none() => {
                peers[r as usize] = Some(c)
            }
            Ok(Some((r, c))) => {
                warn!(peer = r, "unexpected second connection; closing it");
                c.close(1u32.into(), b"duplicate");
            }
            Ok(None) => bail!("the peer listener stopped"),
            Err(_) => {
                *suspects = awaited(&peers);
                let missing: Vec<String> = suspects
                    .iter()
                    .map(|&r| describe(&setup.peers, r))
                    .collect();
                bail!(
                    "peers {} did not connect within {:.1} s",
                    missing.join(", "),
                    mesh_timeout.as_secs_f64()
                );
            }
        }
    }
    // The mesh is complete: later connections are refused.
    let _ = token_tx.send(None);
    ep.set_server_config(None);
    // A shared-memory segment to each peer on this host, announced over the (pinned,
    // token-checked) connection before any piece.
    let mut shm_out: Vec<Option<ShmWriter>> = Vec::with_capacity(n as usize);
    for (r, c) in peers.iter().enumerate() {
        match c {
            Some(c) if setup.shm_peers[r] => {
                let w = ShmWriter::create().with_context(|| {
                    format!(
                        "creating a shared-memory segment for {}",
                        describe(&setup.peers, r as u32)
                    )
                })?;
                let id = w.id();
                let msg = PeerMsg::ShmSegment {
                    name: id.name,
                    pid: id.pid,
                    fd: id.fd,
                };
                if let Err(e) = with_timeout(
                    mesh_timeout,
                    "announcing a segment",
                    send_uni(c, &wire::encode_meta(&msg), &[]),
                )
                .await
                {
                    suspects.push(r as u32);
                    bail!(
                        "announcing the segment to {}: {e}",
                        describe(&setup.peers, r as u32)
                    );
                }
                shm_out.push(Some(w));
            }
            _ => shm_out.push(None),
        }
    }
    let shm_count = shm_out.iter().filter(|w| w.is_some()).count();
    info!(
        rank,
        shared_memory_peers = shm_count,
        quic_peers = n as usize - 1 - shm_count,
        "peer transports"
    );
    // Bounded in count and in bytes (`peer_budget`): a peer that floods pieces stalls the
    // readers (and through QUIC flow control, itself) instead of growing this worker's memory.
    let (ev_tx, ev_rx) = mpsc::channel(PEER_EVENTS);
    // Four of the largest pieces, whatever the run's size (the exchange holds what it has
    // taken under its own limit): a reservation past it takes the whole budget, so the
    // largest piece always gets through once the queue drains.
    let budget = PieceBudget::new(limits.max_bulk.saturating_mul(4));
    for (r, c) in peers.iter().enumerate() {
        if let Some(c) = c {
            let what = describe(&setup.peers, r as u32);
            tokio::spawn(read_peer(
                r as u32,
                what,
                c.clone(),
                limits,
                u32::try_from(setup.max_pixels).unwrap_or(u32::MAX),
                setup.shm_peers[r],
                scene.composite.lz4,
                timeout,
                budget.clone(),
                ev_tx.clone(),
            ));
        }
    }
    let mut engine = tokio::task::block_in_place(|| Engine::new(&scene))
        .context("opening the scene's stores")?;
    // Re-splits measure leaves by their tiles' CPU time (`cluster.rebalance_clock`).
    engine.tile_cpu_clock = true;
    let mut exchange = Exchange::new(
        rank,
        n as usize,
        ExchangeLimits::for_ranks(n as usize, limits.max_bulk),
    );
    for &r in &setup.absent {
        exchange.handle_lost(r, "given up on during set-up".into());
    }
    exchange.skip_to(setup.next_frame);
    if shm_count > 0 {
        // Pieces for peers on this host are encoded straight into their segments.
        exchange.set_sink(Box::new(ShmSink { writers: shm_out }));
    }
    let node = Node {
        rank,
        setup,
        peers,
        engine,
        exchange,
        plans: HashMap::new(),
        timeout,
        gather_shm: None,
        canvases: Default::default(),
        suspects: Vec::new(),
        deferred: Default::default(),
        front_last: None,
        lz4: false,
        earlier: Default::default(),
        cpus: crate::affinity::allowed()
            .map(|c| crate::affinity::format_list(&c))
            .unwrap_or_default(),
        _acceptor: acceptor,
    };
    Ok((node, ev_rx))
}

fn describe(peers: &[PeerInfo], r: u32) -> String {
    match peers.get(r as usize) {
        Some(p) => format!("worker {r} ({} at {})", p.name, p.addr),
        None => format!("worker {r}"),
    }
}

/// Accepts peer connections; each must open with `PeerMsg::Hello` carrying the run token
/// and a rank whose certificate (from the coordinator's set-up) is the one the peer
/// presented in the handshake: peers pin each other, not only the dialling side.
async fn accept_peers(
    ep: quinn::Endpoint,
    token: watch::Receiver<Option<[u8; 32]>>,
    out: mpsc::UnboundedSender<(u32, quinn::Connection)>,
    fingerprints: Vec<wire::Fingerprint>,
) {
    let n = fingerprints.len() as u32;
    let fingerprints = Arc::new(fingerprints);
    // At most this many handshakes at once (every other rank of the run, twice, and some to
    // spare), as the coordinator bounds its own: strangers cannot queue unbounded work.
    let pending = Arc::new(tokio::sync::Semaphore::new((2 * n as usize + 16).max(64)));
    while let Some(incoming) = ep.accept().await {
        let Ok(permit) = pending.clone().try_acquire_owned() else {
            warn!(remote = %incoming.remote_address(), "refused a peer connection: too many handshakes in progress");
            incoming.refuse();
            continue;
        };
        let token = *token.borrow();
        let out = out.clone();
        let fingerprints = fingerprints.clone();
        tokio::spawn(async move {
            // Held until this connection is accepted or refused.
            let _permit = permit;
            let remote = incoming.remote_address();
            // Bounded, as the coordinator bounds its own: QUIC's idle timer restarts with
            // every packet, so a stranger that keeps sending could hold the permit for good.
            let handshake = with_timeout(
                Duration::from_secs(10),
                "peer handshake",
                std::future::IntoFuture::into_future(incoming),
            );
            let conn = match handshake.await {
                Ok(c) => c,
                Err(e) => {
                    warn!(%remote, "peer handshake failed: {e:#}");
                    return;
                }
            };
            let hello = async {
                let mut s =
                    with_timeout(Duration::from_secs(10), "peer hello", conn.accept_uni()).await?;
                let f = with_timeout(
                    Duration::from_secs(10),
                    "peer hello",
                    read_frame(&mut s, &Limits::HANDSHAKE),
                )
                .await?;
                Ok::<_, NetError>(wire::decode_meta::<PeerMsg>(&f.meta)?)
            };
            let presented = strata_net::tls::peer_fingerprint(&conn);
            match (hello.await, token) {
                (Ok(PeerMsg::Hello { token: t, rank }), Some(tok))
                    if strata_net::secret::ct_eq(&t, &tok) && rank < n =>
                {
                    let expected = &fingerprints[rank as usize];
                    if presented.is_some_and(|p| strata_net::secret::ct_eq(&p, expected)) {
                        debug!(peer = rank, %remote, "peer connected");
                        transport::trust(&conn);
                        let welcome = wire::encode_meta(&PeerMsg::Welcome);
                        match with_timeout(
                            Duration::from_secs(10),
                            "peer welcome",
                            send_uni(&conn, &welcome, &[]),
                        )
                        .await
                        {
                            Ok(_) => {
                                let _ = out.send((rank, conn));
                            }
                            Err(e) => warn!(peer = rank, %remote, "welcoming a peer failed: {e}"),
                        }
                    } else {
                        warn!(
                            %remote,
                            "refused a peer connection: it claims rank {rank} but presented certificate {}, not rank {rank}'s {}",
                            presented.map_or("none".into(), |p| strata_net::tls::to_hex(&p)),
                            strata_net::tls::to_hex(expected)
                        );
                        conn.close(2u32.into(), b"refused");
                    }
                }
                (r, _) => {
                    warn!(%remote, "refused a peer connection: {}", match r {
                        Ok(_) => "wrong run token or rank".to_string(),
                        Err(e) => e.to_string(),
                    });
                    conn.close(2u32.into(), b"refused");
                }
            }
        });
    }
}

/// Reads and parses a peer's pieces until its connection ends: inline on QUIC streams,
/// or, for a peer on this host, announced on a stream and read from its shared-memory
/// segment. Parsing here, off the frame's critical path, overlaps it with the frame's
/// waits; a malformed piece ends the connection with an error naming the peer.
#[allow(clippy::too_many_arguments)]
async fn read_peer(
    rank: u32,
    what: String,
    conn: quinn::Connection,
    limits: Limits,
    max_pixels: u32,
    shm_allowed: bool,
    lz4_allowed: bool,
    stream_timeout: Duration,
    budget: PieceBudget,
    out: mpsc::Sender<PeerEvent>,
) {
    let mut shm: Option<ShmReader> = None;
    let err = loop {
        let mut s = match conn.accept_uni().await {
            Ok(s) => s,
            Err(e) => break e.to_string(),
        };
        // A stream, once opened, must arrive whole within the frame timeout: a half-sent
        // one would otherwise block every later piece of this peer.
        let mut f = match with_timeout(
            stream_timeout,
            "a piece stream",
            read_frame(&mut s, &limits),
        )
        .await
        {
            Ok(f) => f,
            Err(e @ NetError::Timeout { .. }) => {
                conn.close(3u32.into(), b"stalled stream");
                break format!("{what} left a stream half-sent: {e}");
            }
            Err(e) => {
                conn.close(3u32.into(), b"malformed frame");
                break format!("malformed frame: {e}");
            }
        };
        let wire_len = f.wire_len();
        let (frame, round, from, piece, wire_len, reserved) =
            match wire::decode_meta::<PeerMsg>(&f.meta) {
                Ok(PeerMsg::Piece {
                    frame,
                    round,
                    from,
                    lz4,
                }) => {
                    if lz4 && !lz4_allowed {
                        conn.close(3u32.into(), b"unasked compression");
                        break format!(
                            "a compressed piece from {what}, in a run without composite.lz4"
                        );
                    }
                    // What the parsed piece will hold, reserved before it is made: an LZ4
                    // block's stated size (checked against the largest piece as it is parsed),
                    // else the buffer it arrived in.
                    let holds = if lz4 {
                        f.bulk
                            .first_chunk::<4>()
                            .map_or(0, |l| u32::from_le_bytes(*l) as u64)
                            .min(wire::max_piece_bytes(max_pixels as u64))
                    } else {
                        f.bulk.len() as u64
                    };
                    let reserved = budget.reserve(holds).await;
                    // The piece keeps the buffer it arrived in (no copy of its pixels).
                    let parsed = tokio::task::block_in_place(|| {
                        if lz4 {
                            SparsePiece::parse_lz4(&f.bulk, max_pixels)
                        } else {
                            SparsePiece::parse_shared(
                                std::mem::take(&mut f.bulk).into(),
                                max_pixels,
                            )
                        }
                    });
                    match parsed {
                        Ok(p) => (frame, round, from, p, wire_len, reserved),
                        Err(e) => {
                            conn.close(3u32.into(), b"malformed piece");
                            break format!("a malformed piece from {what}: {e}");
                        }
                    }
                }
                Ok(PeerMsg::ShmSegment { name, pid, fd }) if shm_allowed && shm.is_none() => {
                    let id = SegmentId { name, pid, fd };
                    match tokio::task::block_in_place(|| ShmReader::open(&id)) {
                        Ok(r) => {
                            debug!(peer = rank, "shared-memory segment open");
                            shm = Some(r);
                            continue;
                        }
                        Err(e) => {
                            conn.close(3u32.into(), b"bad segment");
                            break format!("cannot use the shared-memory segment of {what}: {e}");
                        }
                    }
                }
                Ok(PeerMsg::ShmPiece {
                    frame,
                    round,
                    from,
                    at,
                }) if shm.is_some() => {
                    // The piece's pixels stay in the mapping (its header and runs are
                    // copied out), which it keeps alive while queued: its bytes are
                    // reserved like a received buffer's. (A length past the limit is
                    // refused by `read_piece`; it reserves no more than the limit.)
                    let reserved = budget.reserve(at.len.min(limits.max_bulk)).await;
                    let reader = shm.as_mut().unwrap();
                    match tokio::task::block_in_place(|| {
                        reader.read_piece(at, limits.max_bulk, frame, round, from, max_pixels)
                    }) {
                        Ok(b) => (
                            frame,
                            round,
                            from,
                            b,
                            wire_len + wire::SHM_RECORD_HEADER as u64 + at.len,
                            reserved,
                        ),
                        // A record that does not hold what its announcement says was overwritten:
                        // after a failed attempt at a frame the sender starts its segment over,
                        // and announcements of the old attempt may still be queued here. The
                        // piece is dropped, not trusted; if it was needed after all, the
                        // exchange's deadline reports the missing piece.
                        Err(e @ strata_net::shm::ShmError::Header { .. }) => {
                            warn!(
                                peer = rank,
                                "dropped a stale or bad shared-memory piece: {e}"
                            );
                            continue;
                        }
                        Err(e) => {
                            conn.close(3u32.into(), b"bad shared-memory record");
                            break format!("a piece in the shared-memory segment of {what}: {e}");
                        }
                    }
                }
                Ok(other) => {
                    conn.close(3u32.into(), b"unexpected message");
                    break format!("unexpected message {other:?}");
                }
                Err(e) => {
                    conn.close(3u32.into(), b"malformed message");
                    break format!("malformed message: {e}");
                }
            };
        let piece = PeerEvent::Piece {
            rank,
            frame,
            round,
            from,
            piece,
            wire_len,
            _budget: reserved,
        };
        if out.send(piece).await.is_err() {
            return;
        }
    };
    let _ = out.send(PeerEvent::Lost { rank, error: err }).await;
}

/// The exchange's sink for pieces to peers on this host: each is encoded straight into
/// this worker's segment for that peer (by rank; `None` for peers over QUIC).
struct ShmSink {
    writers: Vec<Option<ShmWriter>>,
}

impl PieceSink for ShmSink {
    fn start_frame(&mut self, _frame: u64) {
        // Every record of the last frame has been used (the frame completed only once
        // every rank had blended all its pieces): the segments start over. After a failed
        // attempt a slow peer may still be blending the old one and see its pixels
        // overwritten; that attempt's result is discarded (results of earlier frames are
        // ignored), so nothing wrong is kept. Pipelined frames would need two halves.
        for w in self.writers.iter_mut().flatten() {
            w.reset();
        }
    }

    fn place(
        &mut self,
        to_rank: u32,
        frame: u64,
        round: u32,
        from: u32,
        segments: &[Segment<'_>],
        layout: &PieceLayout,
        span: Span,
        format: WireFormat,
    ) -> Option<wire::ShmRef> {
        let w = self.writers.get_mut(to_rank as usize)?.as_mut()?;
        w.write_piece(frame, round, from, segments, layout, span, format)
            .map_err(|e| warn!(peer = to_rank, "piece over QUIC instead: {e}"))
            .ok()
    }

    fn forget_peer(&mut self, rank: u32) {
        // The segment's memory (allocated up front, up to the largest frame's pieces).
        if let Some(w) = self.writers.get_mut(rank as usize) {
            *w = None;
        }
    }
}

/// Control messages a frame keeps for after it ([`Node::defer`]).
const MAX_DEFERRED: usize = 64;

/// Compositing plans a worker keeps (one per frame size, rank count and choice); past
/// that they are built again.
const MAX_PLANS: usize = 16;

struct Node {
    /// The cache counters of the engines of this worker's earlier set-ups.
    earlier: crate::cache::CacheStats,
    rank: u32,
    setup: Setup,
    peers: Vec<Option<quinn::Connection>>,
    engine: Engine,
    /// The compositing exchange across frames (early pieces, sender checks, deadlines).
    exchange: Exchange,
    plans: HashMap<(usize, u32, CompositeChoice), Arc<Plan>>,
    timeout: Duration,
    /// The segment for the final pieces (a coordinator on this host).
    gather_shm: Option<ShmWriter>,
    /// The coordinator's canvases this worker has mapped.
    canvases: crate::canvas_cache::CanvasCache<CanvasWriter>,
    /// The peers the last failed frame is blamed on (reported to the coordinator).
    suspects: Vec<u32>,
    /// Control messages that arrived during a frame, for after it.
    deferred: std::collections::VecDeque<CoordMsg>,
    /// This frame's pieces over QUIC are LZ4-compressed (`composite.lz4`).
    lz4: bool,
    /// Cross-worker occlusion: the last frame's transmittance of what lies in front of this
    /// worker, the prediction for the next frame.
    front_last: Option<FrontLast>,
    /// The CPUs this process may run on (`WorkerFrameStats::cpus`).
    cpus: String,
    /// The peer listener of this mesh (idle once it is complete; stopped with the node).
    _acceptor: AbortOnDrop,
}

/// The front transmittance of the last frame and what it depended on (the image size and
/// the workers in front of this one). A re-split of the leaves keeps it: like a moving
/// camera it only makes the prediction worse, and the fix-up keeps the image right.
struct FrontLast {
    width: u32,
    height: u32,
    order: Vec<u32>,
    front: FrontTransmittance,
    /// The frame's camera.
    camera: strata_common::scene::Camera,
}

/// Test hook (debug builds only, what the tests run; release binaries ignore it):
/// `STRATA_TEST_FAULT=RANK:kill|stop|hang|slowMS:PHASE` (several separated by commas) makes
/// worker RANK SIGKILL or SIGSTOP itself, block the calling thread for good (`hang`) or
/// sleep MS milliseconds and go on (`slow2500`), at PHASE: `setup` (on its first set-up,
/// before it dials its peers), `ready` (meshed, before it says so) or, in frame 0, `render`
/// (before rendering), `exchange` (after rendering, before sending anything), `round` or
/// `round0` (with its first round's pieces sent), `roundN` (with round N's pieces sent) or
/// `gather` (before its final piece goes to the coordinator). At `render`, RANK may be
/// `@POS`: the worker at position POS of frame 0's visibility order. Tests check that a
/// vanished or hung worker at any of these moments costs a re-render, or fails the frame
/// naming it.
fn test_fault(rank: u32, frame: u64, phase: &str) {
    test_fault_at(rank, None, frame, phase)
}

/// [`test_fault`] for a worker at visibility position `position`.
fn test_fault_at(rank: u32, position: Option<usize>, frame: u64, phase: &str) {
    if !cfg!(debug_assertions) || frame != 0 {
        return;
    }
    let Ok(specs) = std::env::var("STRATA_TEST_FAULT") else {
        return;
    };
    let me = |r: &str| r == rank.to_string() || position.is_some_and(|p| r == format!("@{p}"));
    let mine = specs.split(',').find_map(|spec| {
        let parts: Vec<&str> = spec.split(':').collect();
        match parts[..] {
            [r, signal, p] if me(r) && p == phase => Some(signal),
            _ => None,
        }
    });
    let Some(signal) = mine else { return };
    if let Some(ms) = signal
        .strip_prefix("slow")
        .and_then(|m| m.parse::<u64>().ok())
    {
        warn!(rank, phase, ms, "STRATA_TEST_FAULT: slow");
        std::thread::sleep(std::time::Duration::from_millis(ms));
        return;
    }
    let sig = match signal {
        "kill" => libc::SIGKILL,
        "stop" => libc::SIGSTOP,
        // The calling thread blocks for good (as on a read that never returns) while the
        // process, its other runtime thread and its connections live on.
        "hang" => {
            warn!(rank, phase, "STRATA_TEST_FAULT: hanging");
            loop {
                std::thread::sleep(std::time::Duration::from_secs(3600));
            }
        }
        _ => return,
    };
    warn!(rank, phase, signal, "STRATA_TEST_FAULT");
    // SAFETY: a plain syscall on our own process.
    unsafe {
        libc::kill(libc::getpid(), sig);
    }
}

/// Parsed pieces and losses queued between the peer readers and the frame loop.
const PEER_EVENTS: usize = 64;

impl Node {
    /// The cache counters since this worker first opened the scene: this set-up's engine's
    /// and its earlier ones'.
    fn cache_totals(&self) -> crate::cache::CacheStats {
        let (a, b) = (self.engine.cache_stats(), self.earlier);
        crate::cache::CacheStats {
            hits: a.hits.saturating_add(b.hits),
            misses: a.misses.saturating_add(b.misses),
            evictions: a.evictions.saturating_add(b.evictions),
            pages_read: a.pages_read.saturating_add(b.pages_read),
            bytes_read: a.bytes_read.saturating_add(b.bytes_read),
            prefetch_dropped: a.prefetch_dropped.saturating_add(b.prefetch_dropped),
            pages_read_at_last_real: a.pages_read_at_last_real.saturating_add(b.pages_read),
            peak_bytes: a.peak_bytes.max(b.peak_bytes),
        }
    }

    /// Renders (or draws) this worker's image and runs its part of the exchange; returns
    /// the stats and the encoded final piece.
    /// The coordinator's canvas `c` for `req`'s frame, mapped on first use (the last few
    /// stay mapped), taken out of the cache until [`put_canvas`](Self::put_canvas).
    fn take_canvas(&mut self, req: &FrameRequest, c: &wire::CanvasRef) -> Result<CanvasWriter> {
        let size = (req.width, req.height);
        if let Some(w) = self.canvases.take(&c.name, size, req.frame) {
            return Ok(w);
        }
        let id = SegmentId {
            name: c.name.clone(),
            pid: c.pid,
            fd: c.fd,
        };
        let w = CanvasWriter::open(&id, req.width, req.height)
            .context("opening the coordinator's canvas")?;
        self.canvases.make_room();
        Ok(w)
    }

    /// Returns a canvas to the cache (most recent last).
    fn put_canvas(&mut self, w: CanvasWriter) {
        self.canvases.put(w);
    }

    /// The final piece for the coordinator when it is not in its canvas: encoded straight
    /// into the gather segment (a coordinator on this host), else encoded (LZ4 with
    /// `composite.lz4`) as bulk for QUIC, which also takes it when the segment cannot (a
    /// host out of memory). Returns the segment record, the bulk, whether it is LZ4 and
    /// the bytes handed over.
    fn send_final(
        &mut self,
        frame: u64,
        piece: &FinalPiece,
    ) -> (Option<wire::ShmRef>, Vec<bytes::Bytes>, bool, u64) {
        let layout = PieceLayout::of(&piece.pixels);
        let rank = self.rank;
        let shm = self.gather_shm.as_mut().and_then(|w| {
            w.reset();
            tokio::task::block_in_place(|| {
                w.write_piece(
                    frame,
                    wire::GATHER_ROUND,
                    rank,
                    &[Segment::Pixels(&piece.pixels)],
                    &layout,
                    piece.span,
                    piece.format,
                )
            })
            .map_err(|e| warn!(frame, "final piece over QUIC instead: {e}"))
            .ok()
        });
        if shm.is_some() {
            return (shm, Vec::new(), false, layout.byte_len(piece.format) as u64);
        }
        let encoded = SparsePiece::encode_with(&piece.pixels, layout, piece.span, piece.format);
        // Compressed in an LZ4 run, unless too large for LZ4's stated length.
        let lz = self
            .lz4
            .then(|| tokio::task::block_in_place(|| encoded.write_lz4()))
            .flatten();
        let lz4 = lz.is_some();
        let bulk: Vec<bytes::Bytes> = match lz {
            Some(b) => vec![b.into()],
            None => encoded.wire_chunks().to_vec(),
        };
        let bytes = bulk.iter().map(|b| b.len() as u64).sum();
        (None, bulk, lz4, bytes)
    }

    /// Takes the canvas back from the exchange (the frame that used it is over).
    fn reclaim_canvas(&mut self) {
        if let Some(t) = self.exchange.take_final_target() {
            let t: Box<dyn std::any::Any> = t;
            if let Ok(t) = t.downcast::<CanvasTarget>() {
                self.put_canvas(t.0);
            }
        }
    }

    /// Puts the frame's final piece into the coordinator's canvas `c`, unless the last
    /// round was already blended there, and returns the span it covers.
    fn write_canvas(
        &mut self,
        req: &FrameRequest,
        c: &wire::CanvasRef,
        piece: &FinalPiece,
    ) -> Result<Span> {
        if piece.placed {
            return Ok(piece.span);
        }
        let mut w = self.take_canvas(req, c)?;
        let r = strata_common::composite::canvas::write_span(
            w.pixels_mut(),
            &frame_interlace(req),
            piece.span,
            &piece.pixels,
        );
        self.put_canvas(w);
        r?;
        Ok(piece.span)
    }

    /// Renders and composites one frame; returns its stats, the final piece, when the
    /// compositing started and the process's CPU time when the frame did.
    async fn frame(
        &mut self,
        req: &FrameRequest,
        events: &mut mpsc::Receiver<PeerEvent>,
        control: &mut mpsc::Receiver<Result<CoordMsg, String>>,
        csend: &mut quinn::SendStream,
    ) -> Result<(WorkerFrameStats, FinalPiece, (Instant, f64))> {
        // Everything sized or indexed from the request is checked first (sans-IO, in
        // `wire`): ranks, leaves and their order, the frame's size, occlusion blocks, wall.
        req.check(
            self.setup.peers.len(),
            self.setup.leaves.len(),
            self.setup.max_pixels,
        )
        .map_err(|e| anyhow!(e))?;
        if let Some(leaves) = &req.leaves {
            // A re-split: new regions from this frame on. The engine keeps its resident
            // pages; those the new regions need are still there.
            info!(
                frame = req.frame,
                leaves = leaves.len(),
                "new regions after a re-split"
            );
            self.setup.leaves = leaves.clone();
        }
        // The ranks of this frame: all of the run, or fewer after the coordinator gave up
        // on lost workers.
        let all = self.setup.peers.len();
        let n = req.order.len();
        // (Checked: the pixel count fits a u32.)
        let px = req.width * req.height;
        let frame_start = Instant::now();
        let cpu_start = process_cpu_s();
        self.lz4 = req.composite.lz4;
        let position = req
            .order
            .iter()
            .position(|&r| r == self.rank)
            .ok_or_else(|| anyhow!("rank {} is missing from the visibility order", self.rank))?;
        let mut stats = WorkerFrameStats {
            rank: self.rank,
            position: position as u32,
            cpus: self.cpus.clone(),
            ..Default::default()
        };
        test_fault_at(self.rank, Some(position), req.frame, "render");
        // 1. The partial image. Under cross-worker occlusion each ray stops where the light
        //    the predicted front transmittance (the last frame's, or a first pass's) lets
        //    through, times its own, falls to 1 − early_termination, and rays behind opaque
        //    blocks are not cast.
        let occlusion = req.occlusion_block > 0 && matches!(req.source, FrameSource::Render);
        let grid = BlockGrid::new(req.width, req.height, req.occlusion_block);
        let threshold = (self.engine.settings.early_termination as f32).min(1.0);
        stats.leaf_cast_s = vec![0.0; self.setup.leaves.len()];
        // Emptied by `image` when a cast has no CPU time (GPU backend, no thread clock).
        stats.leaf_cpu_s = vec![0.0; self.setup.leaves.len()];
        let mut predicted = if occlusion {
            self.predicted_front(req, grid)
        } else {
            None
        }
        .map(|(front, shift)| {
            stats.occlusion_shift = shift;
            front
        });
        if occlusion && req.occlusion_prepass > 0 && req.wall.is_none() {
            // 0. No prediction for some worker: all take one from a first pass at
            //    1/scale of the resolution (its own map exchange).
            //    The last worker's pass would hide nothing behind it: it only waits for its
            //    map. The first has nothing in front: its pass only serves the others.
            let tp = Instant::now();
            let scale = req.occlusion_prepass.clamp(1, MAX_BLOCK);
            let (pw, ph) = (req.width.div_ceil(scale), req.height.div_ceil(scale));
            let low = if req.order.last() == Some(&self.rank) {
                PartialImage::empty(pw, ph)
            } else {
                tokio::task::block_in_place(|| {
                    self.first_pass(req, (pw, ph), &mut stats)
                        .map(|l| composite_leaves(pw, ph, &l))
                })?
            };
            let pre_grid = BlockGrid::new(pw, ph, 1);
            let pre = self
                .occlusion_front(req, pre_grid, &low, true, control, csend, frame_start)
                .await?;
            predicted = (req.order.first() != Some(&self.rank)).then(|| pre.upsampled(grid));
            stats.occlusion_shift = [0, 0];
            stats.prepass_s = tp.elapsed().as_secs_f64();
        }
        let t = Instant::now();
        let limits = predicted.as_ref().map(|front| RayLimits {
            front,
            only: None,
            threshold,
        });
        let size = (req.width, req.height);
        let mut leaves = tokio::task::block_in_place(|| self.image(req, size, limits, &mut stats))?;
        // One leaf is the image; several are composited and kept for the occlusion check.
        let mut image = if leaves.len() == 1 {
            leaves.pop().expect("one leaf")
        } else {
            composite_leaves(req.width, req.height, &leaves)
        };
        if predicted.is_none() {
            leaves = Vec::new();
        }
        stats.render_s = t.elapsed().as_secs_f64();
        if occlusion {
            // 1b. This frame's front transmittance: blocks where the prediction promised
            //     less light than there is are cast again with this frame's thresholds.
            let t = Instant::now();
            // A frame that did not converge (round limit, full atlas) may be drawn again
            // from other pages, less opaque than now, where its blocks are re-cast: its
            // coverage would let the workers behind stop too early, by more than 1 − t. It
            // reports none (clear) instead.
            let converged = stats.outcome == Outcome::Converged.as_str();
            let clear;
            let cover = if converged {
                &image
            } else {
                clear = PartialImage::empty(req.width, req.height);
                &clear
            };
            let front = self
                .occlusion_front(req, grid, cover, false, control, csend, frame_start)
                .await?;
            stats.occlusion_s = t.elapsed().as_secs_f64();
            if let Some(p) = &predicted {
                let hidden = p.hidden(threshold);
                stats.occluded_blocks = hidden.count();
                stats.limited_blocks =
                    p.q.iter().filter(|&&q| q < CLEAR).count() as u64 - stats.occluded_blocks;
                // Each leaf's own alpha tells whether its rays stopped short.
                let own: Vec<&PartialImage> = if leaves.is_empty() {
                    vec![&image]
                } else {
                    leaves.iter().collect()
                };
                let stale = p.stale(&front, &own, threshold);
                drop(own);
                leaves.clear();
                if stale.any() {
                    let t = Instant::now();
                    stats.fixup_blocks = stale.count();
                    let limits = Some(RayLimits {
                        front: &front,
                        only: Some(&stale),
                        threshold,
                    });
                    let mut again =
                        tokio::task::block_in_place(|| self.image(req, size, limits, &mut stats))?;
                    // (One leaf, the usual case: its image as it is, not a copy.)
                    let again = match again.len() {
                        1 => again.pop().expect("one leaf"),
                        _ => composite_leaves(req.width, req.height, &again),
                    };
                    image = replace_blocks(image, &again, &stale);
                    stats.fixup_s = t.elapsed().as_secs_f64();
                }
                debug!(
                    frame = req.frame,
                    hidden = stats.occluded_blocks,
                    limited = stats.limited_blocks,
                    recast = stats.fixup_blocks,
                    "occlusion"
                );
            }
            self.front_last = Some(FrontLast {
                width: req.width,
                height: req.height,
                order: req.order.clone(),
                front,
                camera: req.camera.clone(),
            });
        }
        // Page records are in CPU seconds when the casts were timed by CPU (see `image`).
        page_work_shares(
            &mut stats.page_work,
            if stats.leaf_cpu_s.is_empty() {
                &stats.leaf_cast_s
            } else {
                &stats.leaf_cpu_s
            },
        );
        stats.render_end_us = strata_net::unix_us();
        stats.render_cpu_s = process_cpu_s() - cpu_start;
        let cache = self.cache_totals();
        stats.pages_read = cache.pages_read;
        stats.bytes_read = cache.bytes_read;
        stats.cache_hits = cache.hits;
        stats.cache_lookups = cache.hits + cache.misses;
        let composite_start = Instant::now();

        test_fault(self.rank, req.frame, "exchange");
        // 2. The exchange.
        let key = (n, px, req.composite.clone());
        let plan = match (&req.wall, self.plans.get(&key)) {
            // A wall: direct send to each tile's driver (IceT's multi-tile direct
            // compositing), its targets following the frame's order.
            (Some(w), _) => {
                let spans = w.geometry.driver_spans(&w.drivers, all);
                let targets: Vec<Span> = req
                    .order
                    .iter()
                    .map(|&r| {
                        let (a, b) = spans[r as usize];
                        Span::new(a, b)
                    })
                    .collect();
                Arc::new(build_plan_to(px, &targets)?)
            }
            (None, Some(p)) => p.clone(),
            (None, None) => {
                let p = Arc::new(req.composite.plan(n, px)?);
                if self.plans.len() >= MAX_PLANS {
                    self.plans.clear();
                }
                self.plans.insert(key, p.clone());
                p
            }
        };
        let interlace = frame_interlace(req);
        let format = req.composite.format;
        // A dense image becomes the compositor's buffer as it is.
        let rc = RankCompositor::from_image(plan.clone(), position, image, &interlace)?;
        // With the coordinator's canvas, the last round is blended straight to the result
        // span's physical rows there (through the interlace map).
        if let Some(c) = req.canvas.as_ref() {
            match tokio::task::block_in_place(|| self.take_canvas(req, c)) {
                Ok(w) => self
                    .exchange
                    .set_final_target(Box::new(CanvasTarget(w, interlace))),
                Err(e) => warn!(frame = req.frame, "the canvas is not usable: {e:#}"),
            }
        }
        // The exchange itself is the sans-IO state machine; this loop only moves its
        // pieces and the time.
        let t_exchange = Instant::now();
        // The exchange's deadline runs from the frame's start, except that a worker that
        // reaches it late (its render, first pass, occlusion wait and re-cast took most of
        // the frame's time) still gives its peers a grace window (a quarter of the margin
        // its timeout leaves the coordinator's, within which the rounds' staggered
        // deadlines also fit): its peers, held on their occlusion maps until it reported,
        // may be a moment behind it, and timing out at once would blame them.
        let grace = strata_common::composite::timeout_margin(self.timeout) / 4;
        let late = t_exchange + grace > frame_start + self.timeout;
        let exchange_from = if late {
            t_exchange + grace - self.timeout
        } else {
            frame_start
        };
        // Starting sends the first round: its pieces are encoded (into peers' segments,
        // which may grow) here, off the async threads.
        tokio::task::block_in_place(|| {
            self.exchange.start_frame(
                req.frame,
                req.order.clone(),
                rc,
                format,
                exchange_from,
                self.timeout,
            )
        });
        let mut sends = Vec::new();
        let mut round_sent: Option<u32> = None;
        let result = loop {
            let before = round_sent;
            while let Some(out) = self.exchange.poll_send() {
                round_sent = Some(out.round);
                sends.push(self.send_piece(out, &mut stats)?);
            }
            if let Some(round) = round_sent.filter(|_| round_sent != before) {
                // This round's pieces are on their way.
                if round == 0 {
                    test_fault(self.rank, req.frame, "round");
                }
                test_fault(self.rank, req.frame, &format!("round{round}"));
            }
            match self.exchange.poll_event() {
                Some(ExchangeEvent::Done { result, .. }) => break result,
                Some(ExchangeEvent::Failed { error, .. }) => {
                    // A worker that came to the exchange late (within its grace window of
                    // its deadline, or past it) cannot tell a hung peer from one held up
                    // behind it: blaming its peers would have the coordinator give up
                    // healthy workers and keep the slow one. It blames no one (the
                    // coordinator then ends the frame with this error).
                    self.suspects = match &error {
                        ExchangeError::Timeout { .. } if late => Vec::new(),
                        ExchangeError::Timeout { missing, .. } => missing.clone(),
                        e => e.rank().into_iter().collect(),
                    };
                    if late && matches!(error, ExchangeError::Timeout { .. }) {
                        bail!(
                            "{}; this worker reached the exchange {:.1} s into the frame, at or past its {:.1} s deadline (its render took the frame's time: raise cluster.frame_timeout_s, or give it less work), so it blames no peer",
                            self.explain(&error),
                            t_exchange.saturating_duration_since(frame_start).as_secs_f64(),
                            self.timeout.as_secs_f64()
                        );
                    }
                    bail!("{}", self.explain(&error))
                }
                None => {}
            }
            let deadline = self
                .exchange
                .poll_timeout()
                .unwrap_or_else(|| Instant::now() + self.timeout);
            tokio::select! {
                ev = events.recv() => match ev {
                    // (The piece's budget is given back at the end of this arm.)
                    Some(PeerEvent::Piece { rank, frame, round, from, piece, wire_len, .. }) => {
                        tokio::task::block_in_place(|| {
                            self.exchange.handle_piece(rank, frame, round, from, piece, wire_len)
                        });
                    }
                    Some(PeerEvent::Lost { rank, error }) => self.exchange.handle_lost(rank, error),
                    None => bail!("peer readers stopped"),
                },
                _ = tokio::time::sleep_until(deadline.into()) => {
                    self.exchange.handle_timeout(Instant::now());
                }
                msg = control.recv() => match msg {
                    // The coordinator gave up on a peer: a frame waiting on it fails now,
                    // not at the idle timeout.
                    Some(Ok(CoordMsg::PeerLost { rank })) => self.peer_given_up(rank)?,
                    // Anything else (the re-run of this frame, shutdown) waits its turn.
                    Some(Ok(m)) => self.defer(m)?,
                    Some(Err(e)) => bail!("{e}"),
                    None => bail!("lost the coordinator"),
                },
            }
        };
        for (what, to_rank, s) in sends {
            // The exchange's own deadline: a worker that came to it late (held behind a
            // slow front worker for its map) keeps its grace window for its sends too. From
            // the frame's start, a send to that slow worker had no time left at all and
            // blamed it whenever the piece waited on its reader.
            let left = (exchange_from + self.timeout).saturating_duration_since(Instant::now());
            // A send that fails or stalls is the receiver's doing (a lost or hung peer):
            // blamed on it, so the coordinator re-renders without it instead of ending
            // the run for want of a suspect.
            let sent = match tokio::time::timeout(left, s).await {
                Ok(Ok(r)) => r,
                Ok(Err(e)) => Err(anyhow!("sending to {what}: {e}")),
                Err(_) => Err(anyhow!(
                    "sending to {what} did not finish within the frame timeout of {:.1} s",
                    self.timeout.as_secs_f64()
                )),
            };
            match sent {
                Ok(bytes) => stats.bytes_sent += bytes,
                Err(e) => {
                    self.suspects = vec![to_rank];
                    return Err(e);
                }
            }
        }
        let x = self.exchange.stats();
        stats.rounds = x.rounds;
        stats.encode_s += x.encode_s;
        stats.blend_s = x.blend_s;
        stats.bytes_received = x.bytes_received;
        stats.exchange_s =
            (t_exchange.elapsed().as_secs_f64() - stats.encode_s - stats.blend_s).max(0.0);
        let result = match &req.wall {
            // The tiles this rank drives go to their files; the coordinator gets nothing.
            Some(w) if !result.span.is_empty() => {
                let t = Instant::now();
                let g = &w.geometry;
                let first = result.span.start / g.tile_pixels();
                tokio::task::block_in_place(|| {
                    write_tiles(g, first, &result.pixels, &w.files, w.background)
                })
                .with_context(|| format!("frame {}: writing its wall tiles", req.frame))?;
                stats.tiles_written = result.span.len() / g.tile_pixels();
                stats.tile_write_s = t.elapsed().as_secs_f64();
                FinalPiece {
                    span: Span::EMPTY,
                    format,
                    pixels: Vec::new(),
                    placed: false,
                }
            }
            _ => result,
        };
        Ok((stats, result, (composite_start, cpu_start)))
    }

    /// Hands one outgoing piece to its transport: written to the peer's shared-memory
    /// segment and announced, or sent inline over QUIC; returns the send task.
    #[allow(clippy::type_complexity)]
    fn send_piece(
        &mut self,
        out: Outgoing,
        stats: &mut WorkerFrameStats,
    ) -> Result<(String, u32, tokio::task::JoinHandle<Result<u64>>)> {
        let to_rank = out.to_rank;
        let conn = self
            .peers
            .get(to_rank as usize)
            .cloned()
            .flatten()
            .ok_or_else(|| anyhow!("no connection to rank {to_rank}"))?;
        // A peer on this host has the piece in its segment already (the exchange's sink
        // encoded it there): only the announcement goes over QUIC. Otherwise the piece.
        let (meta, chunks) = match out.piece {
            OutgoingPiece::Placed(at) => {
                let moved = wire::SHM_RECORD_HEADER as u64 + at.len;
                stats.shm_bytes_sent += moved;
                stats.bytes_sent += moved;
                let meta = wire::encode_meta(&PeerMsg::ShmPiece {
                    frame: out.frame,
                    round: out.round,
                    from: out.from,
                    at,
                });
                (meta, Vec::new())
            }
            OutgoingPiece::Encoded(piece) => {
                let te = Instant::now();
                // The piece's own buffers go to the stream as they are (no joined copy).
                // Compressed in an LZ4 run, unless too large for LZ4's stated length.
                let lz = self
                    .lz4
                    .then(|| tokio::task::block_in_place(|| piece.write_lz4()))
                    .flatten();
                let lz4 = lz.is_some();
                let chunks = match lz {
                    Some(b) => vec![b.into()],
                    None => piece.wire_chunks().to_vec(),
                };
                stats.encode_s += te.elapsed().as_secs_f64();
                let meta = wire::encode_meta(&PeerMsg::Piece {
                    frame: out.frame,
                    round: out.round,
                    from: out.from,
                    lz4,
                });
                (meta, chunks)
            }
        };
        let what = describe(&self.setup.peers, to_rank);
        let task_what = what.clone();
        Ok((
            what,
            to_rank,
            tokio::spawn(async move {
                send_uni_chunks(&conn, &meta, chunks)
                    .await
                    .map_err(|e| anyhow!("sending to {task_what}: {e}"))
            }),
        ))
    }

    /// An exchange failure in words, with the peer it is about named.
    fn explain(&self, error: &ExchangeError) -> String {
        let peers = &self.setup.peers;
        match error {
            ExchangeError::WrongPosition { rank, claimed, frame } => format!(
                "{} sent a piece as position {claimed} of frame {frame}, which is not its position",
                describe(peers, *rank)
            ),
            ExchangeError::TooFarAhead { rank, frame, current, ahead } => format!(
                "{} sent a piece for frame {frame}, more than {ahead} frames after frame {current}",
                describe(peers, *rank)
            ),
            ExchangeError::PendingFull { rank, pieces, bytes } => format!(
                "{} sent more early pieces than this worker buffers ({pieces} pieces, {bytes} bytes)",
                describe(peers, *rank)
            ),
            ExchangeError::BadPiece { rank, source } => {
                format!("piece from {}: {source}", describe(peers, *rank))
            }
            ExchangeError::Timeout { frame, round, missing, secs } => format!(
                "no piece from {} (round {round} of frame {frame}) within the frame timeout of {secs:.1} s",
                missing
                    .iter()
                    .map(|&r| describe(peers, r))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
            ExchangeError::PeerLost { rank, error } => {
                format!("lost the connection to {}: {error}", describe(peers, *rank))
            }
            other => other.to_string(),
        }
    }

    /// The last frame's front transmittance, when it applies to this frame (same image
    /// size and workers in front, and something in front), moved or widened by the
    /// camera's motion since, with the shift applied in blocks (`[0, 0]` when widened).
    fn predicted_front(
        &self,
        req: &FrameRequest,
        grid: BlockGrid,
    ) -> Option<(FrontTransmittance, [i32; 2])> {
        let last = self.front_last.as_ref()?;
        // The same workers in front of this one (their order among themselves does not
        // matter: opacity composes either way).
        let front = |order: &[u32]| -> Option<Vec<u32>> {
            let pos = order.iter().position(|&r| r == self.rank)?;
            let mut f = order[..pos].to_vec();
            f.sort_unstable();
            Some(f)
        };
        let same = last.width == req.width
            && last.height == req.height
            && front(&last.order).is_some()
            && front(&last.order) == front(&req.order)
            && last.front.grid == grid;
        // A moved camera moves what is in front: widen the map by the motion the coordinator
        // measured (in blocks, rounded up).
        let radius = req
            .occlusion_motion
            .min(req.width.max(req.height))
            .div_ceil(grid.block.max(1));
        if !(same && last.front.any()) {
            return None;
        }
        if radius > 0 {
            return Some((last.front.dilated(radius), [0, 0]));
        }
        // Otherwise the map moves with this worker's region: by the median displacement of
        // the region's points on screen, rounded to blocks (none for a wall, whose image is
        // its tiles stacked). On the demo orbit (3° a frame, p = 8) that left about a fifth
        // fewer blocks to cast again than the unmoved map (docs/BENCHMARKS.md).
        let (dx, dy) = match req.wall {
            None => self.region_shift(&last.camera, req).unwrap_or((0.0, 0.0)),
            Some(_) => (0.0, 0.0),
        };
        let b = grid.block.max(1) as f64;
        // A shift of a whole side or more clears the map, so it is clamped there (and so
        // fits an i32 whatever the motion).
        let blocks = |d: f64, side: u32| {
            let side = side as f64;
            (d / b).round().clamp(-side, side) as i32
        };
        let shift = [blocks(dx, grid.cols()), blocks(dy, grid.rows())];
        Some((last.front.shifted(shift[0] as i64, shift[1] as i64), shift))
    }

    /// How far this worker's region (the box around its leaves) moved on screen from
    /// `camera` to `req`'s, in pixels ([`strata_common::camera::screen_shift`]); `None` when
    /// either camera makes no view.
    fn region_shift(
        &self,
        camera: &strata_common::scene::Camera,
        req: &FrameRequest,
    ) -> Option<(f64, f64)> {
        if *camera == req.camera {
            return Some((0.0, 0.0));
        }
        let s = &self.engine.settings;
        let a = View::new(camera, s, req.width, req.height).ok()?;
        let b = View::new(&req.camera, s, req.width, req.height).ok()?;
        let bounds = self
            .setup
            .leaves
            .iter()
            .copied()
            .reduce(|u, l| u.union(&l))?;
        Some(strata_common::camera::screen_shift(&a, &b, &bounds))
    }

    /// Sends this worker's block transmittance to the coordinator and waits for the
    /// transmittance of what the workers in front of it hold this frame. The first worker
    /// of the visibility order has nothing in front: it does not wait (the coordinator
    /// sends it no map), which matters because, casting every ray in full, it is often
    /// the slowest. The last has no one behind it and sends nothing.
    async fn occlusion_front(
        &mut self,
        req: &FrameRequest,
        grid: BlockGrid,
        image: &PartialImage,
        prepass: bool,
        control: &mut mpsc::Receiver<Result<CoordMsg, String>>,
        csend: &mut quinn::SendStream,
        frame_start: Instant,
    ) -> Result<FrontTransmittance> {
        let deadline = frame_start + self.timeout;
        // The map comes when the workers in front have reported; a worker in front that
        // hangs is the coordinator's to blame, at its own frame timeout (later than this
        // worker's, `Setup::timeout_ms`), which it ends by giving that worker up
        // (`PeerLost`) or the run. Failing here first would blame no one.
        let map_deadline = frame_start + 2 * self.timeout;
        // Nothing lies behind the last worker of the order: no one needs its coverage.
        if req.order.last() != Some(&self.rank) {
            let map = tokio::task::block_in_place(|| Transmittance::of_image(image, grid.block));
            let msg = WorkerMsg::Coverage {
                frame: req.frame,
                rect: map.rect,
                prepass,
            };
            let left = deadline.saturating_duration_since(Instant::now());
            with_timeout(
                left,
                "sending the occlusion coverage to the coordinator",
                write_frame(csend, &wire::encode_meta(&msg), &encode_levels(&map.q)),
            )
            .await?;
        }
        if req.order.first() == Some(&self.rank) {
            return Ok(FrontTransmittance::clear(grid));
        }
        loop {
            let left = map_deadline.saturating_duration_since(Instant::now());
            let msg = match tokio::time::timeout(left, control.recv()).await {
                Ok(Some(Ok(m))) => m,
                Ok(Some(Err(e))) => bail!("{e}"),
                Ok(None) => bail!("lost the coordinator"),
                Err(_) => bail!(
                    "no occlusion map for frame {} from the coordinator within {:.1} s",
                    req.frame,
                    (2 * self.timeout).as_secs_f64()
                ),
            };
            match msg {
                CoordMsg::Occlusion {
                    frame,
                    front,
                    prepass: p,
                } if frame == req.frame && p == prepass => {
                    return FrontTransmittance::decoded(grid, &front).with_context(|| {
                        format!("the coordinator's occlusion map for frame {frame}")
                    });
                }
                // The map of an abandoned attempt at an earlier frame.
                CoordMsg::Occlusion { frame, .. } if frame < req.frame => {
                    debug!(frame, "ignoring a stale occlusion map")
                }
                CoordMsg::Occlusion { frame, .. } => {
                    bail!(
                        "the coordinator sent the occlusion map of frame {frame} during frame {}",
                        req.frame
                    )
                }
                // The coordinator gave up on a peer: this attempt is over if it takes part.
                CoordMsg::PeerLost { rank } => {
                    self.peer_given_up(rank)?;
                    if req.order.contains(&rank) {
                        self.suspects = vec![rank];
                        bail!(
                            "the coordinator gave up {} before the occlusion map of frame {}",
                            describe(&self.setup.peers, rank),
                            req.frame
                        );
                    }
                }
                other => self.defer(other)?,
            }
        }
    }

    /// Closes every peer connection with `code` and `reason`.
    fn close_peers(&self, code: u32, reason: &[u8]) {
        for c in self.peers.iter().flatten() {
            c.close(code.into(), reason);
        }
    }

    /// The coordinator gave up on peer `rank`: frames waiting on it fail now. A rank that
    /// is not another worker of the run is refused (this worker's own would fail every
    /// later frame).
    fn peer_given_up(&mut self, rank: u32) -> Result<()> {
        anyhow::ensure!(
            rank != self.rank && (rank as usize) < self.setup.peers.len(),
            "the coordinator gave up rank {rank}, which is not a peer of rank {} in a run of {}",
            self.rank,
            self.setup.peers.len()
        );
        self.exchange
            .handle_lost(rank, "the coordinator gave it up".into());
        // Its connection too (a peer given up may still be alive, its frame thread stuck):
        // its reader task ends, and nothing of it is kept for the rest of the set-up.
        if let Some(c) = self.peers.get(rank as usize).and_then(Option::as_ref) {
            c.close(4u32.into(), b"given up");
        }
        Ok(())
    }

    /// Keeps a control message that came during a frame for after it, up to
    /// [`MAX_DEFERRED`] of them (a frame's re-run, a shutdown, a new set-up: a few).
    fn defer(&mut self, m: CoordMsg) -> Result<()> {
        anyhow::ensure!(
            self.deferred.len() < MAX_DEFERRED,
            "the coordinator sent more than {MAX_DEFERRED} messages during one frame"
        );
        self.deferred.push_back(m);
        Ok(())
    }

    /// This worker's leaf `leaf` (an index from the coordinator, checked).
    fn leaf(&self, leaf: u32) -> Result<strata_common::kd::Region> {
        self.setup
            .leaves
            .get(leaf as usize)
            .copied()
            .ok_or_else(|| anyhow!("leaf {leaf} is not one of this worker's"))
    }

    /// Occlusion's first pass: each leaf cast once at `width × height` with the pages
    /// resident now (no loads: a first pass that asked for its own coarser pages would
    /// read more than it saves).
    fn first_pass(
        &mut self,
        req: &FrameRequest,
        (width, height): (u32, u32),
        stats: &mut WorkerFrameStats,
    ) -> Result<Vec<PartialImage>> {
        let view = View::new(&req.camera, &self.engine.settings, width, height)?;
        let mut images = Vec::new();
        for &leaf in &req.leaf_order {
            let region = self.leaf(leaf)?;
            let f = self.engine.render_frame(&view, &region)?;
            stats.cast_s += f.seconds;
            stats.samples += f.stats.samples;
            images.push(f.image);
        }
        Ok(images)
    }

    /// This worker's partial images for the frame, one per leaf, front to back (one for
    /// a synthetic frame), its rays limited by `limits` (cross-worker occlusion). Adds its
    /// costs to `stats` (so a re-cast adds to the first render).
    fn image(
        &mut self,
        req: &FrameRequest,
        (width, height): (u32, u32),
        limits: Option<RayLimits<'_>>,
        stats: &mut WorkerFrameStats,
    ) -> Result<Vec<PartialImage>> {
        match &req.source {
            FrameSource::Synthetic { coverage, seed } => Ok(vec![synthetic_image(
                req.width,
                req.height,
                self.rank,
                self.setup.peers.len() as u32,
                *coverage,
                *seed ^ req.frame,
            )]),
            FrameSource::Render => {
                let view = match &req.wall {
                    Some(w) => View::wall(&req.camera, &self.engine.settings, &w.geometry)?,
                    None => View::new(&req.camera, &self.engine.settings, width, height)?,
                };
                let mut images = Vec::new();
                let mut outcome = Outcome::Converged;
                let n = self.setup.leaves.len();
                stats
                    .leaf_cast_s
                    .resize(n.max(stats.leaf_cast_s.len()), 0.0);
                if !stats.leaf_cpu_s.is_empty() {
                    stats.leaf_cpu_s.resize(n.max(stats.leaf_cpu_s.len()), 0.0);
                }
                let threads = rayon::current_num_threads().max(1) as f64;
                for &leaf in &req.leaf_order {
                    let region = self.leaf(leaf)?;
                    let r = self.engine.render_batch_limited(&view, &region, limits)?;
                    stats.render_rounds = stats.render_rounds.max(r.rounds);
                    stats.cast_s += r.cast_seconds;
                    stats.load_s += r.load_seconds;
                    add_per_round(&mut stats.round_cast_s, &r.round_cast_seconds);
                    add_per_round(&mut stats.round_load_s, &r.round_load_seconds);
                    stats.last_round_s += r.last_seconds;
                    stats.leaf_cast_s[leaf as usize] += r.last_seconds;
                    // A leaf's CPU time over the render threads; without one (GPU backend,
                    // no thread clock) the worker reports none at all, so that the
                    // coordinator never takes a leaf that cast nothing (off screen: 0 s)
                    // for a worker that cannot say.
                    let cpu = r
                        .last_cpu_seconds
                        .map(|c| c / threads)
                        .filter(|_| !stats.leaf_cpu_s.is_empty());
                    match cpu {
                        Some(c) => stats.leaf_cpu_s[leaf as usize] += c,
                        None => {
                            // From here on every leaf is in wall time: the page records of
                            // earlier leaves, in CPU time, would be divided by wall times.
                            if !stats.leaf_cpu_s.is_empty() {
                                stats.page_work.clear();
                            }
                            stats.leaf_cpu_s.clear()
                        }
                    }
                    if req.page_work {
                        // Seconds of this cast per page, for now (a re-cast adds its own);
                        // `page_work_shares` turns them into shares of the leaf's time, in
                        // the same clock. The tiles' CPU time where there is one: a tile
                        // the system descheduled for a while did not cost its pages that
                        // time.
                        let tiles = r.tiles.iter().map(|t| {
                            let s = if cpu.is_some() {
                                t.cpu_seconds
                            } else {
                                t.seconds
                            };
                            (&t.feedback[..], s)
                        });
                        let s = cpu.unwrap_or(r.last_seconds) as f32;
                        stats.page_work.extend(
                            crate::feedback::page_shares(tiles)
                                .into_iter()
                                .map(|(key, share)| PageWork {
                                    leaf,
                                    key,
                                    share: share * s,
                                }),
                        );
                    }
                    stats.backend = r.backend.clone();
                    push_distinct(&mut stats.effects, &r.variant.effects.to_string());
                    push_distinct(&mut stats.variant, &r.variant_name);
                    stats.samples += r.last.samples;
                    stats.rays += r.last.rays;
                    if r.outcome != Outcome::Converged {
                        outcome = r.outcome;
                    }
                    images.push(r.image);
                }
                // A fix-up render keeps the first render's outcome unless it is worse.
                if stats.outcome.is_empty() || outcome != Outcome::Converged {
                    stats.outcome = outcome.as_str().into();
                }
                Ok(images)
            }
        }
    }
}

/// Adds each round's seconds into the entry of its round.
fn add_per_round(sums: &mut Vec<f64>, rounds: &[f64]) {
    if sums.len() < rounds.len() {
        sums.resize(rounds.len(), 0.0);
    }
    for (s, r) in sums.iter_mut().zip(rounds) {
        *s += r;
    }
}

/// CPU seconds this process has used so far, user and system, all threads (0 if the
/// system will not say).
fn process_cpu_s() -> f64 {
    let mut u = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: `getrusage` fills the struct it is given; on failure it is left zeroed.
    let u = unsafe {
        if libc::getrusage(libc::RUSAGE_SELF, u.as_mut_ptr()) != 0 {
            return 0.0;
        }
        u.assume_init()
    };
    let s = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    s(u.ru_utime) + s(u.ru_stime)
}

/// Turns page records holding seconds (one per leaf, page and cast: a re-cast adds its
/// own) into [`PageWork`] shares of each leaf's measured time `leaf_s`: merged per leaf and
/// page, divided by the leaf's time, without records of no time or of an unknown or untimed
/// leaf, and at most [`MAX_PAGE_WORK`] of them (the largest; the rest of a leaf's time goes
/// unattributed).
fn page_work_shares(work: &mut Vec<PageWork>, leaf_s: &[f64]) {
    work.sort_unstable_by_key(|w| (w.leaf, w.key));
    let mut out: Vec<PageWork> = Vec::with_capacity(work.len());
    for w in work.drain(..) {
        match out.last_mut() {
            Some(o) if (o.leaf, o.key) == (w.leaf, w.key) => o.share += w.share,
            _ => out.push(w),
        }
    }
    out.retain_mut(|w| match leaf_s.get(w.leaf as usize) {
        Some(&t) if t > 0.0 && t.is_finite() => {
            w.share = (w.share as f64 / t) as f32;
            w.share > 0.0 && w.share.is_finite()
        }
        _ => false,
    });
    if out.len() > MAX_PAGE_WORK {
        out.sort_unstable_by(|a, b| b.share.total_cmp(&a.share));
        out.truncate(MAX_PAGE_WORK);
    }
    *work = out;
}

/// Appends `item` to the `; `-joined list `list` unless it is there already.
fn push_distinct(list: &mut String, item: &str) {
    if !list.split("; ").any(|x| x == item) {
        if !list.is_empty() {
            list.push_str("; ");
        }
        list.push_str(item);
    }
}

/// Leaf images, front to back, composited into one.
fn composite_leaves(width: u32, height: u32, leaves: &[PartialImage]) -> PartialImage {
    match leaves {
        [] => PartialImage::empty(width, height),
        [one] => one.clone(),
        _ => {
            let refs: Vec<&PartialImage> = leaves.iter().collect();
            let full = composite_front_to_back(width, height, &refs);
            PartialImage::from_full(width, height, &full)
        }
    }
}

/// `base` with the pixels of the blocks set in `blocks` taken from `again` (a re-cast of
/// those blocks). In place when every such block lies inside `base`'s rectangle (a few
/// hundred blocks of a frame: rewriting the whole frame around them took longer than
/// casting them), else into a rectangle grown to hold the blocks' new content.
fn replace_blocks(
    mut base: PartialImage,
    again: &PartialImage,
    blocks: &BlockMask,
) -> PartialImage {
    let set: Vec<usize> = (0..blocks.grid.len()).filter(|&b| blocks.get(b)).collect();
    let r = base.rect;
    let inside = set.iter().all(|&b| {
        let (x0, y0, x1, y1) = blocks.grid.pixels_of(b);
        x0 >= r.x && y0 >= r.y && x1 <= r.x + r.w && y1 <= r.y + r.h
    });
    if inside {
        for &b in &set {
            let (x0, y0, x1, y1) = blocks.grid.pixels_of(b);
            for y in y0..y1 {
                let row = ((y - r.y) * r.w) as usize;
                for x in x0..x1 {
                    base.pixels[row + (x - r.x) as usize] = again.get(x, y);
                }
            }
        }
        return base;
    }
    // Some blocks lie outside the base's rectangle: grow it to hold the re-cast's content
    // in them (not to the whole frame: a full-frame copy and its scan cost more than the
    // re-cast at p = 8). Pixels the rectangle gains outside the blocks stay transparent.
    let ar = again.rect;
    let mut grown = r;
    for &b in &set {
        let (x0, y0, x1, y1) = blocks.grid.pixels_of(b);
        let (cx0, cy0) = (x0.max(ar.x), y0.max(ar.y));
        let (cx1, cy1) = (x1.min(ar.x + ar.w), y1.min(ar.y + ar.h));
        if cx0 < cx1 && cy0 < cy1 {
            grown = grown.union(&Rect {
                x: cx0,
                y: cy0,
                w: cx1 - cx0,
                h: cy1 - cy0,
            });
        }
    }
    let gw = grown.w as usize;
    let mut pixels = vec![[0.0f32; 4]; grown.area()];
    for y in 0..r.h {
        let at = (r.y + y - grown.y) as usize * gw + (r.x - grown.x) as usize;
        let row = (y * r.w) as usize;
        pixels[at..at + r.w as usize].copy_from_slice(&base.pixels[row..row + r.w as usize]);
    }
    for &b in &set {
        let (x0, y0, x1, y1) = blocks.grid.pixels_of(b);
        let (cx0, cy0) = (x0.max(grown.x), y0.max(grown.y));
        let (cx1, cy1) = (x1.min(grown.x + grown.w), y1.min(grown.y + grown.h));
        for y in cy0..cy1 {
            let row = (y - grown.y) as usize * gw;
            for x in cx0..cx1 {
                pixels[row + (x - grown.x) as usize] = again.get(x, y);
            }
        }
    }
    PartialImage {
        width: base.width,
        height: base.height,
        rect: grown,
        pixels,
    }
}

/// The row interlacing of `req`'s frame: one group per rank in the frame's order, none for
/// a wall (its tiles are runs of whole rows).
fn frame_interlace(req: &FrameRequest) -> Interlace {
    Interlace::new(
        req.width,
        req.height,
        req.order.len() as u32,
        req.composite.interlace && req.wall.is_none(),
    )
}

/// The coordinator's canvas as the exchange's final target, with the frame's interlace
/// map (the canvas is the physical frame).
struct CanvasTarget(CanvasWriter, Interlace);

impl FinalTarget for CanvasTarget {
    fn frame(&mut self) -> Option<(&mut [Rgba], Interlace)> {
        Some((self.0.pixels_mut(), self.1))
    }
}

/// A benchmark image: a translucent box's footprint for rank `rank` of `ranks`, covering
/// `coverage` of the frame (every pixel when `coverage >= 1`), with smoothly varying
/// premultiplied colour. Deterministic in `seed`.
pub fn synthetic_image(
    width: u32,
    height: u32,
    rank: u32,
    ranks: u32,
    coverage: f32,
    seed: u64,
) -> PartialImage {
    let (w, h) = if coverage >= 1.0 {
        (width, height)
    } else {
        let s = coverage.max(0.0).sqrt();
        (
            ((width as f32 * s).round() as u32).clamp(1, width),
            ((height as f32 * s).round() as u32).clamp(1, height),
        )
    };
    // Boxes of different ranks sit at different places, as the projections of the k-d
    // leaves of a scene do.
    let mix =
        strata_common::digest::fmix64(seed ^ (rank as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15));
    let x = if w < width {
        (mix % (width - w + 1) as u64) as u32
    } else {
        0
    };
    let y = if h < height {
        ((mix >> 32) % (height - h + 1) as u64) as u32
    } else {
        0
    };
    let alpha = 0.2 + 0.6 * (rank as f32 + 0.5) / ranks.max(1) as f32;
    let mut pixels = Vec::with_capacity(w as usize * h as usize);
    for j in 0..h {
        for i in 0..w {
            let a = alpha * (0.5 + 0.5 * ((i + j + rank) % 64) as f32 / 64.0);
            let c: Rgba = [
                a * (i as f32 / w as f32),
                a * (j as f32 / h as f32),
                a * 0.5,
                a,
            ];
            pixels.push(c);
        }
    }
    PartialImage {
        width,
        height,
        rect: Rect { x, y, w, h },
        pixels,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_common::image::Rect;

    fn image(w: u32, h: u32, rect: Rect, seed: f32) -> PartialImage {
        let pixels = (0..rect.area())
            .map(|i| {
                let v = (i as f32 * 0.37 + seed).fract();
                [v * 0.5, v * 0.25, v * 0.125, v]
            })
            .collect();
        PartialImage {
            width: w,
            height: h,
            rect,
            pixels,
        }
    }

    /// Seconds per leaf, page and cast become shares of each leaf's time: a re-cast's
    /// seconds add to the first cast's, untimed and unknown leaves drop out.
    #[test]
    fn page_work_becomes_shares_of_each_leafs_time() {
        let w = |leaf, key, share| PageWork { leaf, key, share };
        // Leaf 0 took 4 s: page 7 had 1 s in the first cast and 1 s in the re-cast, page 3
        // had 1 s; leaf 1 was not timed; leaf 5 does not exist; a record of no time.
        let mut work = vec![
            w(0, 7, 1.0),
            w(1, 7, 2.0),
            w(0, 3, 1.0),
            w(5, 1, 1.0),
            w(0, 7, 1.0),
            w(0, 9, 0.0),
        ];
        page_work_shares(&mut work, &[4.0, 0.0]);
        assert_eq!(work, [w(0, 3, 0.25), w(0, 7, 0.5)]);
        // Over the cap, the largest shares stay.
        let mut many: Vec<PageWork> = (0..MAX_PAGE_WORK as u64 + 2)
            .map(|k| w(0, k, if k == 0 { 1.0 } else { 1e-6 }))
            .collect();
        page_work_shares(&mut many, &[1.0]);
        assert_eq!(many.len(), MAX_PAGE_WORK);
        assert!(many.iter().any(|p| p.key == 0 && p.share == 1.0));
    }

    /// Blocks inside the base's rectangle are replaced in place, others by growing the
    /// rectangle; either way the frame is the base with exactly those blocks' pixels taken
    /// from the re-cast, and the rectangle holds every pixel with content.
    #[test]
    fn replace_blocks_takes_exactly_the_blocks() {
        let (w, h) = (24, 16);
        let grid = BlockGrid::new(w, h, 4);
        let base = image(
            w,
            h,
            Rect {
                x: 4,
                y: 2,
                w: 14,
                h: 12,
            },
            0.1,
        );
        let again = image(
            w,
            h,
            Rect {
                x: 0,
                y: 0,
                w: 20,
                h: 16,
            },
            0.7,
        );
        for blocks in [vec![7usize, 8, 14], vec![7, 0], vec![]] {
            let mut mask = BlockMask::empty(grid);
            for &b in &blocks {
                mask.set(b);
            }
            let got = replace_blocks(base.clone(), &again, &mask);
            // The rectangle grows only as far as the re-cast's content.
            let bound = base.rect.union(&again.rect);
            let gr = got.rect;
            assert!(
                gr.x >= bound.x
                    && gr.y >= bound.y
                    && gr.x + gr.w <= bound.x + bound.w
                    && gr.y + gr.h <= bound.y + bound.h,
                "{gr:?} outside {bound:?}"
            );
            assert_eq!(got.pixels.len(), gr.area());
            let got = got.to_full();
            for y in 0..h {
                for x in 0..w {
                    let want = if mask.pixel(x, y) {
                        again.get(x, y)
                    } else {
                        base.get(x, y)
                    };
                    assert_eq!(
                        got[(y * w + x) as usize],
                        want,
                        "blocks {blocks:?} ({x}, {y})"
                    );
                }
            }
        }
    }
}
