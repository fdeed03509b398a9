//! Latency and loss in user space, where the kernel has no `sch_netem`.
//!
//! The switch namespace routes every packet between two hosts through a TUN device; a thread
//! of the test, attached to that device from inside the namespace, holds each packet for a
//! fixed delay and drops a seeded-random fraction of them, then writes it back, and the
//! kernel routes it on to its destination. Packets keep their order (one delay for all, one
//! queue), as `netem delay` without jitter does. The packets are the kernel's own: QUIC sees
//! real datagrams delayed and lost between real sockets.

use std::collections::VecDeque;
use std::ffi::CString;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// What the relay did: every packet it read was either forwarded or dropped.
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct Counts {
    pub(crate) forwarded: u64,
    pub(crate) dropped: u64,
    /// The shortest and longest time a forwarded packet was held (read to written).
    pub(crate) min_held: Duration,
    pub(crate) max_held: Duration,
}

/// A running relay; stops (and its device goes down with the namespace) on `finish`/drop.
pub(crate) struct Relay {
    stop: Arc<AtomicBool>,
    counts: Arc<Mutex<Counts>>,
    thread: Option<JoinHandle<()>>,
}

impl Relay {
    /// The counts so far.
    pub(crate) fn counts(&self) -> Counts {
        *self.counts.lock().unwrap()
    }

    /// Stops the relay and returns its counts.
    pub(crate) fn finish(mut self) -> Counts {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.take().unwrap().join().unwrap();
        self.counts()
    }
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// `struct ifreq` as TUNSETIFF reads it: the name, the flags, padding to 40 bytes.
#[repr(C)]
struct IfReq {
    name: [u8; libc::IFNAMSIZ],
    flags: libc::c_short,
    _pad: [u8; 22],
}
const _: () = assert!(std::mem::size_of::<IfReq>() == 40);

/// `_IOW('T', 202, int)`.
const TUNSETIFF: libc::c_ulong = 0x4004_54ca;

fn os_err(what: &str) -> String {
    format!("{what}: {}", std::io::Error::last_os_error())
}

/// Moves the calling thread (only) into network namespace `netns` (made by `ip netns add`).
pub(crate) fn enter(netns: &str) -> Result<(), String> {
    let path = CString::new(format!("/run/netns/{netns}")).unwrap();
    // SAFETY: plain system calls on a descriptor this function owns.
    unsafe {
        let ns = libc::open(path.as_ptr(), libc::O_RDONLY | libc::O_CLOEXEC);
        if ns < 0 {
            return Err(os_err(&format!("opening /run/netns/{netns}")));
        }
        let r = libc::setns(ns, libc::CLONE_NEWNET);
        libc::close(ns);
        if r != 0 {
            return Err(os_err(&format!("entering namespace {netns}")));
        }
    }
    Ok(())
}

/// Enters network namespace `netns` (this thread only) and attaches to its TUN device `dev`.
fn attach(netns: &str, dev: &str) -> Result<libc::c_int, String> {
    enter(netns)?;
    // SAFETY: plain system calls on descriptors this function owns; `req` outlives the ioctl.
    unsafe {
        let fd = libc::open(
            c"/dev/net/tun".as_ptr(),
            libc::O_RDWR | libc::O_NONBLOCK | libc::O_CLOEXEC,
        );
        if fd < 0 {
            return Err(os_err("opening /dev/net/tun"));
        }
        let mut req = IfReq {
            name: [0; libc::IFNAMSIZ],
            flags: (libc::IFF_TUN | libc::IFF_NO_PI) as libc::c_short,
            _pad: [0; 22],
        };
        req.name[..dev.len()].copy_from_slice(dev.as_bytes());
        if libc::ioctl(fd, TUNSETIFF, &mut req as *mut IfReq) != 0 {
            let e = os_err(&format!("attaching to TUN device {dev}"));
            libc::close(fd);
            return Err(e);
        }
        Ok(fd)
    }
}

/// Starts relaying on TUN device `dev` of namespace `netns` (made with `ip tuntap add`):
/// every packet held for `delay`, a fraction `loss` dropped (seeded by `seed`). Returns once
/// the device is attached, or why it could not be.
pub(crate) fn start(
    netns: &str,
    dev: &str,
    delay: Duration,
    loss: f64,
    seed: u64,
) -> Result<Relay, String> {
    assert!(dev.len() < libc::IFNAMSIZ && (0.0..1.0).contains(&loss));
    let stop = Arc::new(AtomicBool::new(false));
    let counts = Arc::new(Mutex::new(Counts::default()));
    let (ready_tx, ready_rx) = std::sync::mpsc::channel();
    let (netns, dev, halt, shared) = (
        netns.to_string(),
        dev.to_string(),
        stop.clone(),
        counts.clone(),
    );
    let thread = std::thread::spawn(move || {
        let fd = match attach(&netns, &dev) {
            Ok(fd) => {
                let _ = ready_tx.send(Ok(()));
                fd
            }
            Err(e) => {
                let _ = ready_tx.send(Err(e));
                return;
            }
        };
        relay(fd, delay, loss, seed, &halt, &shared);
        // SAFETY: `fd` is this thread's, and nothing uses it after this.
        unsafe { libc::close(fd) };
    });
    match ready_rx.recv() {
        Ok(Ok(())) => Ok(Relay {
            stop,
            counts,
            thread: Some(thread),
        }),
        Ok(Err(e)) => {
            let _ = thread.join();
            Err(e)
        }
        Err(_) => Err("the relay thread ended before attaching".into()),
    }
}

/// The loop: read what has arrived, queue it (or drop it), write what is due, sleep in
/// `poll` until the next packet is due or one arrives. Ends when told to, or when reading
/// fails (the device is gone): the test then sees packets stop being forwarded.
fn relay(
    fd: libc::c_int,
    delay: Duration,
    loss: f64,
    seed: u64,
    stop: &AtomicBool,
    shared: &Mutex<Counts>,
) {
    let mut counts = Counts {
        min_held: Duration::MAX,
        ..Counts::default()
    };
    // splitmix64; drop when the top 53 bits of a draw, as a fraction, fall under `loss`.
    let mut state = seed;
    let mut lost = move || {
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
        ((z >> 11) as f64 / (1u64 << 53) as f64) < loss
    };
    let mut queue: VecDeque<(Instant, Instant, Vec<u8>)> = VecDeque::new();
    let mut buf = vec![0u8; 65536];
    while !stop.load(Ordering::Relaxed) {
        loop {
            // SAFETY: `buf` is valid for its length.
            let n = unsafe { libc::read(fd, buf.as_mut_ptr().cast(), buf.len()) };
            if n < 0 {
                let e = std::io::Error::last_os_error();
                if !matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::Interrupted
                ) {
                    eprintln!("impair: reading the TUN device: {e}");
                    return;
                }
            }
            if n <= 0 {
                break;
            }
            let now = Instant::now();
            if lost() {
                counts.dropped += 1;
            } else {
                queue.push_back((now, now + delay, buf[..n as usize].to_vec()));
            }
        }
        let now = Instant::now();
        while queue.front().is_some_and(|(_, due, _)| *due <= now) {
            let (read_at, _, p) = queue.pop_front().unwrap();
            // SAFETY: `p` is valid for its length. A failed write is a packet lost, as on a
            // full link.
            unsafe { libc::write(fd, p.as_ptr().cast(), p.len()) };
            let held = now - read_at;
            counts.forwarded += 1;
            counts.min_held = counts.min_held.min(held);
            counts.max_held = counts.max_held.max(held);
        }
        {
            let mut c = shared.lock().unwrap();
            *c = counts;
            if c.forwarded == 0 {
                c.min_held = Duration::ZERO;
            }
        }
        let wait = queue
            .front()
            .map_or(Duration::from_millis(20), |(_, due, _)| {
                due.saturating_duration_since(now)
            });
        let mut p = libc::pollfd {
            fd,
            events: libc::POLLIN,
            revents: 0,
        };
        let ts = libc::timespec {
            tv_sec: wait.as_secs() as libc::time_t,
            tv_nsec: wait.subsec_nanos() as libc::c_long,
        };
        // SAFETY: one valid pollfd; `ts` outlives the call.
        unsafe { libc::ppoll(&mut p, 1, &ts, std::ptr::null()) };
    }
}
