//! Temporary outputs removed when a signal ends the process.
//!
//! A build writes a hidden temporary file beside its output and renames it when complete
//! (`builder`); an error or a panic removes it as the build unwinds. A signal (Ctrl-C,
//! `kill`, a closed terminal) ends the process without unwinding, which left the
//! temporary behind: hundreds of GB for a real survey. While a temporary is registered here,
//! SIGINT, SIGTERM and SIGHUP first unlink every registered temporary, then end the process
//! as the signal would have (default action, re-raised), so its exit status still says
//! which signal ended it. A signal the process ignores stays ignored. The handlers the
//! process had before are restored once no temporary is registered.

use std::ffi::CString;
use std::os::unix::ffi::OsStrExt;
use std::path::Path;
use std::sync::atomic::{AtomicPtr, Ordering};
use std::sync::Mutex;

/// Temporaries registered at once (concurrent builds in one process).
const SLOTS: usize = 64;

/// The registered paths, as C strings the handler can pass to `unlink` (which is
/// async-signal-safe; nothing else the handler does allocates or locks).
static PATHS: [AtomicPtr<libc::c_char>; SLOTS] =
    [const { AtomicPtr::new(std::ptr::null_mut()) }; SLOTS];

const SIGNALS: [libc::c_int; 3] = [libc::SIGINT, libc::SIGTERM, libc::SIGHUP];

/// How many temporaries are registered, and the handlers to restore after the last.
static INSTALLED: Mutex<(usize, Vec<libc::sigaction>)> = Mutex::new((0, Vec::new()));

/// A registered temporary; dropping it unregisters it (the file is the caller's to
/// remove or rename).
pub struct Registered {
    slot: Option<usize>,
}

/// Registers `path` to be unlinked if a signal ends the process before the returned
/// value is dropped. With every slot taken the path is not registered (the build still
/// removes it on errors).
pub fn register(path: &Path) -> Registered {
    let Ok(c) = CString::new(path.as_os_str().as_bytes()) else {
        return Registered { slot: None };
    };
    // Never freed: a handler may still read a pointer just unregistered. One short
    // string per build.
    let raw = c.into_raw();
    let slot = PATHS.iter().position(|p| {
        p.compare_exchange(
            std::ptr::null_mut(),
            raw,
            Ordering::SeqCst,
            Ordering::SeqCst,
        )
        .is_ok()
    });
    if slot.is_some() {
        let mut g = INSTALLED.lock().unwrap_or_else(|e| e.into_inner());
        if g.0 == 0 {
            g.1 = SIGNALS.iter().map(|&s| install(s)).collect();
        }
        g.0 += 1;
    }
    Registered { slot }
}

impl Drop for Registered {
    fn drop(&mut self) {
        let Some(slot) = self.slot else { return };
        PATHS[slot].store(std::ptr::null_mut(), Ordering::SeqCst);
        let mut g = INSTALLED.lock().unwrap_or_else(|e| e.into_inner());
        g.0 -= 1;
        if g.0 == 0 {
            for (&s, old) in SIGNALS.iter().zip(&g.1) {
                // SAFETY: restores the action `install` saved for this signal.
                unsafe { libc::sigaction(s, old, std::ptr::null_mut()) };
            }
        }
    }
}

/// Installs `on_signal` for `signal`; returns the action it replaced. A signal the
/// process ignores (SIGHUP under `nohup`, SIGINT in a background job of a script) stays
/// ignored: it never ended the build, and must not start to.
fn install(signal: libc::c_int) -> libc::sigaction {
    // SAFETY: plain-data structs, filled by `sigaction`; the handler is async-signal-safe.
    unsafe {
        let mut new: libc::sigaction = std::mem::zeroed();
        new.sa_sigaction = on_signal as extern "C" fn(libc::c_int) as libc::sighandler_t;
        libc::sigemptyset(&mut new.sa_mask);
        let mut old: libc::sigaction = std::mem::zeroed();
        libc::sigaction(signal, &new, &mut old);
        if old.sa_sigaction == libc::SIG_IGN {
            libc::sigaction(signal, &old, std::ptr::null_mut());
        }
        old
    }
}

extern "C" fn on_signal(signal: libc::c_int) {
    for p in &PATHS {
        let path = p.load(Ordering::SeqCst);
        if !path.is_null() {
            // SAFETY: registered pointers are never freed; `unlink` is async-signal-safe.
            unsafe { libc::unlink(path) };
        }
    }
    // SAFETY: all async-signal-safe. The signal is blocked while its handler runs: raised
    // again and unblocked, its default action ends the process here. Should another thread
    // have put a handler back in between, `_exit` does.
    unsafe {
        libc::signal(signal, libc::SIG_DFL);
        libc::raise(signal);
        let mut set: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut set);
        libc::sigaddset(&mut set, signal);
        libc::pthread_sigmask(libc::SIG_UNBLOCK, &set, std::ptr::null_mut());
        libc::_exit(128 + signal);
    }
}
