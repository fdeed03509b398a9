//! The run's shared secret and random tokens.

use anyhow::{bail, Context, Result};
use ring::rand::SecureRandom;
use std::path::Path;

/// Default environment variable holding the shared secret.
pub const SECRET_ENV: &str = "STRATA_SECRET";

/// `N` bytes from the operating system's CSPRNG.
pub fn random_bytes<const N: usize>() -> [u8; N] {
    let mut b = [0u8; N];
    ring::rand::SystemRandom::new()
        .fill(&mut b)
        .expect("the OS random source failed");
    b
}

/// A new secret as 64 hex digits (printable, so it can go through files and environment).
pub fn new_secret() -> Vec<u8> {
    random_bytes::<32>()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect::<String>()
        .into_bytes()
}

/// The shared secret: the first line of `file` (surrounding whitespace removed) if given,
/// else the variable `env`. `Ok(None)` when neither is set.
pub fn read_secret(file: Option<&Path>, env: &str) -> Result<Option<Vec<u8>>> {
    if let Some(f) = file {
        let text = std::fs::read(f)
            .with_context(|| format!("cannot read the secret file {}", f.display()))?;
        let s = text
            .split(|&b| b == b'\n')
            .next()
            .unwrap_or_default()
            .trim_ascii();
        if s.len() < 16 {
            bail!(
                "{}: the secret must be at least 16 bytes on its first line, found {}",
                f.display(),
                s.len()
            );
        }
        warn_if_exposed(f);
        return Ok(Some(s.to_vec()));
    }
    match std::env::var_os(env) {
        Some(v) => {
            let s = v.as_encoded_bytes().trim_ascii().to_vec();
            if s.len() < 16 {
                bail!(
                    "${env}: the secret must be at least 16 bytes, found {}",
                    s.len()
                );
            }
            Ok(Some(s))
        }
        None => Ok(None),
    }
}

/// Logs a warning when every user of this machine can read the secret file `f`: it is
/// readable by all, and so is the way to it (its folder lets every user in). Not an error:
/// the default umask makes files readable by all, and a folder of one's own (as
/// `configs/slurm-render.sh` makes, mode 700) keeps them private.
fn warn_if_exposed(f: &Path) {
    use std::os::unix::fs::PermissionsExt;
    let dir = match f.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mode = |p: &Path| std::fs::metadata(p).map(|m| m.permissions().mode());
    if let (Ok(file), Ok(folder)) = (mode(f), mode(dir)) {
        if readable_by_all(file, folder) {
            tracing::warn!(
                "the secret file {} can be read by every user of this machine (mode {:o}, its folder {:o}): chmod o-r it, or keep it in a folder of your own",
                f.display(),
                file & 0o7777,
                folder & 0o7777
            );
        }
    }
}

/// Whether every user may read a file with permission bits `file` in a folder with
/// permission bits `folder` (which must let them search it, `o+x`).
fn readable_by_all(file: u32, folder: u32) -> bool {
    file & 0o004 != 0 && folder & 0o001 != 0
}

/// Constant-time equality (length is not secret).
pub fn ct_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_secret_file_is_exposed_only_where_every_user_reaches_and_reads_it() {
        assert!(readable_by_all(0o644, 0o755));
        assert!(readable_by_all(0o604, 0o711));
        assert!(!readable_by_all(0o640, 0o755)); // group only
        assert!(!readable_by_all(0o600, 0o777));
        assert!(!readable_by_all(0o644, 0o700)); // a private folder (the Slurm script's)
        assert!(!readable_by_all(0o644, 0o754)); // listable, not searchable
    }

    #[test]
    fn secrets() {
        assert!(ct_eq(b"abc", b"abc"));
        assert!(!ct_eq(b"abc", b"abd"));
        assert!(!ct_eq(b"abc", b"ab"));
        assert_eq!(new_secret().len(), 64);
        assert_ne!(new_secret(), new_secret());
        let dir = std::env::temp_dir().join(format!("strata-secret-{}", std::process::id()));
        std::fs::write(&dir, "  0123456789abcdef0123\nignored\n").unwrap();
        assert_eq!(
            read_secret(Some(&dir), "STRATA_NO_SUCH_VAR")
                .unwrap()
                .unwrap(),
            b"0123456789abcdef0123"
        );
        std::fs::write(&dir, "short\n").unwrap();
        assert!(read_secret(Some(&dir), "X").is_err());
        std::fs::remove_file(&dir).unwrap();
        assert!(read_secret(None, "STRATA_NO_SUCH_VAR_EITHER")
            .unwrap()
            .is_none());
    }
}
