//! The `--connect` command line shared by `worker` and `coordinator worker` (the form in
//! which a coordinator spawns local workers from its own executable, so the two can never
//! be of different builds).

use anyhow::{Context, Result};
use std::net::{SocketAddr, ToSocketAddrs};
use std::path::PathBuf;
use std::time::Duration;

/// Joining a render run.
#[derive(clap::Args)]
pub struct JoinArgs {
    /// Coordinator address (HOST:PORT) to join.
    #[arg(long, value_name = "HOST:PORT")]
    pub connect: Option<String>,
    /// The coordinator's certificate fingerprint (64 hex digits), as it printed it.
    #[arg(long, conflicts_with = "fingerprint_file")]
    pub fingerprint: Option<String>,
    /// File with the coordinator's fingerprint (written by `[cluster] fingerprint_file`).
    #[arg(long, value_name = "FILE")]
    pub fingerprint_file: Option<PathBuf>,
    /// File whose first line is the run's shared secret; otherwise the variable named by
    /// --secret-env.
    #[arg(long, value_name = "FILE")]
    pub secret_file: Option<PathBuf>,
    /// Environment variable holding the shared secret.
    #[arg(long, default_value = "STRATA_SECRET")]
    pub secret_env: String,
    /// Name in logs and errors (default: HOST:PID).
    #[arg(long)]
    pub name: Option<String>,
    /// Local UDP address for this worker's endpoint (peers connect to it); default: any
    /// interface of the coordinator's address family, any port.
    #[arg(long)]
    pub bind: Option<SocketAddr>,
    /// Seconds to keep trying to reach the coordinator.
    #[arg(long, default_value_t = 60.0)]
    pub connect_timeout_s: f64,
    /// Seconds of silence after which the coordinator counts as gone.
    #[arg(long, default_value_t = 10.0)]
    pub idle_timeout_s: f64,
    /// First QUIC datagram size in bytes, 1200..=65527 (the coordinator's
    /// `cluster.quic_mtu`): larger only where every link carries it (jumbo frames).
    #[arg(long, default_value_t = 1200, value_parser = clap::value_parser!(u16).range(1200..=65527))]
    pub quic_mtu: u16,
}

/// Joins the run described by `a`; returns when the coordinator shuts the run down.
pub fn join(a: JoinArgs) -> Result<()> {
    use strata_net::tls::parse_fingerprint;
    let connect = a.connect.context("--connect HOST:PORT is required")?;
    let addr = connect
        .to_socket_addrs()
        .with_context(|| format!("--connect {connect}: cannot resolve"))?
        .next()
        .with_context(|| format!("--connect {connect}: no address"))?;
    let fingerprint = match (&a.fingerprint, &a.fingerprint_file) {
        (Some(f), _) => parse_fingerprint(f).context("--fingerprint")?,
        (None, Some(file)) => read_fingerprint_file(file)?,
        (None, None) => anyhow::bail!(
            "--fingerprint or --fingerprint-file is required: a worker only talks to the coordinator it was told to pin"
        ),
    };
    let secret = strata_net::secret::read_secret(a.secret_file.as_deref(), &a.secret_env)?
        .with_context(|| {
            format!(
                "no shared secret: pass --secret-file or set ${}",
                a.secret_env
            )
        })?;
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .unwrap_or_else(|_| "host".into());
    let bind = a.bind.unwrap_or(if addr.is_ipv6() {
        "[::]:0".parse().unwrap()
    } else {
        "0.0.0.0:0".parse().unwrap()
    });
    // The coordinator's bound (`cluster.*_timeout_s`): a duration from infinity or NaN
    // would panic.
    for (flag, v) in [
        ("--connect-timeout-s", a.connect_timeout_s),
        ("--idle-timeout-s", a.idle_timeout_s),
    ] {
        anyhow::ensure!(
            v > 0.0 && v <= 1e6,
            "{flag} must be a positive number of seconds up to 1e6, got {v}"
        );
    }
    crate::node::run(crate::node::NodeOptions {
        connect: addr,
        fingerprint,
        secret: strata_common::wire::Secret(secret),
        name: a
            .name
            .unwrap_or_else(|| format!("{host}:{}", std::process::id())),
        bind,
        connect_timeout: Duration::from_secs_f64(a.connect_timeout_s),
        idle_timeout: Duration::from_secs_f64(a.idle_timeout_s),
        quic_mtu: a.quic_mtu,
    })
}

/// Reads the coordinator's fingerprint from `file`. The file decides which server gets the
/// secret, so it is refused where another user could rewrite or replace it: the file
/// itself every user may write, or owned by another user than this worker's or root
/// ([`untrusted_file`]), or any folder on its real path (links resolved) every user may
/// write and not sticky ([`untrusted_dir`]). The file is checked and read through one open
/// handle, so a link re-pointed in between changes nothing.
fn read_fingerprint_file(file: &std::path::Path) -> Result<strata_common::wire::Fingerprint> {
    use std::io::Read;
    use std::os::unix::fs::MetadataExt;
    let cannot = || format!("cannot read {}", file.display());
    let real = std::fs::canonicalize(file).with_context(cannot)?;
    let f = std::fs::File::open(&real).with_context(cannot)?;
    let meta = f.metadata().with_context(cannot)?;
    if !meta.is_file() {
        anyhow::bail!("{}: not a file", file.display());
    }
    // SAFETY: geteuid has no preconditions and cannot fail.
    let me = unsafe { libc::geteuid() };
    if let Some(why) = untrusted_file(meta.mode(), meta.uid(), me) {
        anyhow::bail!(
            "{}: {why}, so another user could name the server this worker sends its secret to",
            file.display()
        );
    }
    for dir in real.ancestors().skip(1) {
        let mode = std::fs::metadata(dir).with_context(cannot)?.mode();
        if let Some(why) = untrusted_dir(mode) {
            anyhow::bail!(
                "{}: the folder {} {why}, so another user could replace the file and name the server this worker sends its secret to",
                file.display(),
                dir.display()
            );
        }
    }
    // A fingerprint is 64 hex digits: more than a few KiB is not one.
    const MAX: u64 = 4096;
    let mut text = String::new();
    f.take(MAX + 1)
        .read_to_string(&mut text)
        .with_context(cannot)?;
    if text.len() as u64 > MAX {
        anyhow::bail!(
            "{}: longer than {MAX} bytes, so not a fingerprint file",
            file.display()
        );
    }
    strata_net::tls::parse_fingerprint(&text).with_context(|| format!("{}", file.display()))
}

/// Why a fingerprint file with permission bits `mode`, owned by user `owner`, must not be
/// trusted by a worker running as user `me`: writable by every user, or owned by another
/// user than `me` or root (who could rewrite it). `None` when it may be trusted.
fn untrusted_file(mode: u32, owner: u32, me: u32) -> Option<String> {
    if mode & 0o002 != 0 {
        return Some(format!(
            "writable by every user (mode {:o}; chmod o-w it)",
            mode & 0o7777
        ));
    }
    if owner != me && owner != 0 {
        return Some(format!(
            "owned by user {owner}, not by this worker's user ({me}) or root"
        ));
    }
    None
}

/// Why a folder with permission bits `mode` lets another user replace a file in it: every
/// user may write it and it is not sticky (as /tmp is, where only a file's owner may
/// remove or rename it). `None` when it does not.
fn untrusted_dir(mode: u32) -> Option<String> {
    (mode & 0o002 != 0 && mode & 0o1000 == 0).then(|| {
        format!(
            "is writable by every user and not sticky (mode {:o})",
            mode & 0o7777
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fingerprint_files_others_could_rewrite_are_untrusted() {
        // Mode: every user may write it.
        assert!(untrusted_file(0o100666, 1000, 1000)
            .unwrap()
            .contains("writable by every user (mode 666"));
        assert!(untrusted_file(0o100602, 0, 1000).is_some());
        // Owner: this user, or root, but no one else.
        assert_eq!(untrusted_file(0o100644, 1000, 1000), None);
        assert_eq!(untrusted_file(0o100664, 1000, 1000), None);
        assert_eq!(untrusted_file(0o100644, 0, 1000), None);
        assert!(untrusted_file(0o100644, 1001, 1000)
            .unwrap()
            .contains("owned by user 1001"));
        assert!(untrusted_file(0o100644, 1001, 0).is_some());
        // Folders: world-writable without the sticky bit.
        assert!(untrusted_dir(0o40777).is_some());
        assert!(untrusted_dir(0o40773).is_some());
        assert_eq!(untrusted_dir(0o41777), None); // /tmp
        assert_eq!(untrusted_dir(0o40755), None);
        assert_eq!(untrusted_dir(0o40775), None);
    }
}
