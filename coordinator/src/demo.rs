//! The built-in synthetic survey of a scene's `[synthetic]` section: generated on first use
//! into its cache folder and reused afterwards.
//!
//! Safe for concurrent processes: an exclusive `flock` on `DIR.lock` (beside the folder)
//! serializes them. The survey is generated into a hidden sibling `.DIRNAME.tmpPID`, the
//! marker `.complete` (`size=NX NY NZ seed=S`) is written into it last, and it is renamed to
//! `DIR`; so a `DIR` with a matching marker is always complete, and an interrupted
//! generation leaves nothing that is mistaken for a survey.

use anyhow::{bail, Context, Result};
use indicatif::ProgressBar;
use std::fs::File;
use std::io::Write;
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use strata_common::scene::SyntheticSpec;

/// Name of the completion marker inside the survey folder.
pub const MARKER: &str = ".complete";

/// Makes sure the synthetic survey of `spec` exists in `spec.dir`, generating it (with
/// `crate::synth::synth`) if it is missing or empty, or holds this cache's survey of
/// another size or seed. A non-empty folder without the cache's marker is refused.
/// Returns whether it generated.
pub fn ensure_synthetic(spec: &SyntheticSpec, progress: &ProgressBar) -> Result<bool> {
    let dir = spec.dir.as_path();
    let name = dir
        .file_name()
        .with_context(|| format!("{}: not a usable synthetic survey folder", dir.display()))?
        .to_string_lossy()
        .into_owned();
    let parent = match dir.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let want = marker_text(spec);
    let marker = dir.join(MARKER);
    // The survey is there: nothing to write, so no lock to take (a survey shared read-only,
    // where the lock file cannot be created, serves every run). A folder is only ever
    // renamed into place whole, marker included.
    if std::fs::read_to_string(&marker).is_ok_and(|have| have.trim() == want) {
        tracing::info!(dir = %dir.display(), "reusing the synthetic survey ({want})");
        return Ok(false);
    }
    std::fs::create_dir_all(&parent)
        .with_context(|| format!("{}: cannot create folder", parent.display()))?;
    let lock_path = parent.join(format!("{name}.lock"));
    let _lock = Lock::exclusive(&lock_path)?;

    match std::fs::read_to_string(&marker) {
        Ok(have) if have.trim() == want => {
            tracing::info!(dir = %dir.display(), "reusing the synthetic survey ({want})");
            return Ok(false);
        }
        Ok(have) => tracing::info!(
            dir = %dir.display(),
            "the cached synthetic survey is {}, the scene asks for {want}: regenerating",
            have.trim()
        ),
        // Generation renames a complete folder into place, so a folder without the marker
        // was never one of ours, whatever its files are called (`coordinator synth` writes
        // the same names): only an empty one is used.
        Err(_) if dir.exists() => {
            let first = std::fs::read_dir(dir)
                .ok()
                .and_then(|mut d| d.next())
                .and_then(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().into_owned());
            if let Some(n) = first {
                bail!(
                    "{}: holds {n:?} but not this cache's marker {MARKER}, so it was not \
                     generated here; refusing to replace it (move it away, or pick another \
                     synthetic.dir)",
                    dir.display()
                );
            }
        }
        Err(_) => {}
    }
    if dir.exists() {
        check_removable(dir)?;
    }

    // Under the lock no other run generates: every temporary of this folder is one an
    // interrupted run left (each a survey's worth of bytes).
    let prefix = format!(".{name}.tmp");
    if let Ok(entries) = std::fs::read_dir(&parent) {
        for e in entries.flatten() {
            let n = e.file_name().to_string_lossy().into_owned();
            if n.starts_with(&prefix) && n[prefix.len()..].bytes().all(|b| b.is_ascii_digit()) {
                let stale = e.path();
                std::fs::remove_dir_all(&stale).with_context(|| {
                    format!("{}: cannot remove a stale temporary", stale.display())
                })?;
            }
        }
    }
    let tmp = parent.join(format!("{prefix}{}", std::process::id()));
    tracing::info!(
        dir = %dir.display(),
        "generating the synthetic survey ({want}); later runs reuse it"
    );
    let result = (|| -> Result<()> {
        crate::synth::synth(&tmp, spec.size, spec.seed, false, progress)?;
        let marker_tmp = tmp.join(MARKER);
        let mut f = File::create(&marker_tmp)
            .with_context(|| format!("{}: cannot create", marker_tmp.display()))?;
        f.write_all(format!("{want}\n").as_bytes())
            .and_then(|()| f.sync_all())
            .with_context(|| format!("{}: cannot write", marker_tmp.display()))?;
        if dir.exists() {
            std::fs::remove_dir_all(dir).with_context(|| {
                format!("{}: cannot remove the stale survey folder", dir.display())
            })?;
        }
        std::fs::rename(&tmp, dir)
            .with_context(|| format!("cannot rename {} to {}", tmp.display(), dir.display()))
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(e.context(format!(
            "{}: cannot generate the synthetic survey",
            dir.display()
        )));
    }
    tracing::info!(dir = %dir.display(), "synthetic survey ready");
    Ok(true)
}

/// The marker's content for `spec`.
fn marker_text(spec: &SyntheticSpec) -> String {
    let [nx, ny, nz] = spec.size;
    format!("size={nx} {ny} {nz} seed={}", spec.seed)
}

/// Refuses to delete a folder that holds anything `synth` does not write (a mistyped
/// `dir` must never cost the user data).
fn check_removable(dir: &Path) -> Result<()> {
    anyhow::ensure!(
        dir.is_dir(),
        "{}: exists and is not a folder; move it away or pick another synthetic.dir",
        dir.display()
    );
    let entries =
        std::fs::read_dir(dir).with_context(|| format!("{}: cannot list", dir.display()))?;
    for e in entries {
        let e = e.with_context(|| format!("{}: cannot list", dir.display()))?;
        let n = e.file_name().to_string_lossy().into_owned();
        // What `synth` writes without SEG-Y and text horizons (this cache never asks for
        // them, so such files are the user's).
        let ours = n == MARKER
            || n == "scene.toml"
            || n == "seismic.strata"
            || (n.starts_with("horizon") && n.ends_with(".strata"))
            || (n.starts_with('.') && n.contains(".tmp"));
        if !ours || !e.file_type().is_ok_and(|t| t.is_file()) {
            bail!(
                "{}: holds {n:?}, which is not part of a synthetic survey; refusing to replace \
                 the folder (move it away or pick another synthetic.dir)",
                dir.display()
            );
        }
    }
    Ok(())
}

/// An exclusive `flock` held until drop (closing the file releases it).
struct Lock {
    _file: File,
}

impl Lock {
    fn exclusive(path: &Path) -> Result<Lock> {
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(path)
            .with_context(|| format!("{}: cannot open the lock file", path.display()))?;
        loop {
            // SAFETY: flock on a file descriptor that `file` keeps open.
            let rc = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX) };
            if rc == 0 {
                return Ok(Lock { _file: file });
            }
            let err = std::io::Error::last_os_error();
            if err.kind() != std::io::ErrorKind::Interrupted {
                return Err(err).with_context(|| format!("{}: cannot lock", path.display()));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(dir: &Path, seed: u64) -> SyntheticSpec {
        SyntheticSpec {
            dir: dir.to_path_buf(),
            size: [24, 20, 16],
            seed,
        }
    }

    fn mtime(p: &Path) -> std::time::SystemTime {
        std::fs::metadata(p).unwrap().modified().unwrap()
    }

    #[test]
    fn generates_once_then_reuses() {
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("cache/demo");
        let s = spec(&dir, 3);
        assert!(ensure_synthetic(&s, &ProgressBar::hidden()).unwrap());
        let cube = dir.join("seismic.strata");
        for f in [
            "seismic.strata",
            "horizon1.strata",
            "horizon2.strata",
            "horizon3.strata",
        ] {
            assert!(dir.join(f).is_file(), "{f}");
        }
        assert_eq!(
            std::fs::read_to_string(dir.join(MARKER)).unwrap().trim(),
            "size=24 20 16 seed=3"
        );
        let before = mtime(&cube);
        std::thread::sleep(std::time::Duration::from_millis(20));
        assert!(!ensure_synthetic(&s, &ProgressBar::hidden()).unwrap());
        assert_eq!(mtime(&cube), before);
        // An interrupted run's temporary (another process's) goes with the next generation.
        let stale = root.path().join("cache/.demo.tmp4242");
        std::fs::create_dir_all(stale.join("x")).unwrap();
        assert!(ensure_synthetic(&spec(&dir, 4), &ProgressBar::hidden()).unwrap());
        assert!(!stale.exists());
        // Only the survey and its lock are left: no temporaries.
        let mut names: Vec<String> = std::fs::read_dir(root.path().join("cache"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(names, ["demo", "demo.lock"]);
    }

    /// A complete survey is reused without taking the lock: a survey shared read-only
    /// (where the lock file cannot be created) serves every run. The lock file's absence
    /// after reuse shows it (root may create files in a read-only folder, so a read-only
    /// folder alone would not).
    #[test]
    fn a_complete_survey_is_reused_without_its_lock() {
        use std::os::unix::fs::PermissionsExt;
        let root = tempfile::tempdir().unwrap();
        let cache = root.path().join("cache");
        let dir = cache.join("demo");
        let s = spec(&dir, 3);
        assert!(ensure_synthetic(&s, &ProgressBar::hidden()).unwrap());
        let lock = cache.join("demo.lock");
        std::fs::remove_file(&lock).unwrap();
        let ro = std::fs::Permissions::from_mode(0o555);
        std::fs::set_permissions(&cache, ro).unwrap();
        let reused = ensure_synthetic(&s, &ProgressBar::hidden());
        std::fs::set_permissions(&cache, std::fs::Permissions::from_mode(0o755)).unwrap();
        assert!(!reused.unwrap(), "regenerated a complete survey");
        assert!(!lock.exists(), "took the lock to reuse a complete survey");
    }

    #[test]
    fn concurrent_callers_generate_once() {
        let root = tempfile::tempdir().unwrap();
        let s = spec(&root.path().join("demo"), 5);
        let results: Vec<bool> = std::thread::scope(|scope| {
            let hs: Vec<_> = (0..2)
                .map(|_| scope.spawn(|| ensure_synthetic(&s, &ProgressBar::hidden()).unwrap()))
                .collect();
            hs.into_iter().map(|h| h.join().unwrap()).collect()
        });
        assert_eq!(results.iter().filter(|&&g| g).count(), 1, "{results:?}");
        assert!(s.dir.join("seismic.strata").is_file());
    }

    #[test]
    fn other_seed_or_incomplete_regenerates() {
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("demo");
        assert!(ensure_synthetic(&spec(&dir, 1), &ProgressBar::hidden()).unwrap());
        let first = std::fs::read(dir.join("seismic.strata")).unwrap();
        assert!(ensure_synthetic(&spec(&dir, 2), &ProgressBar::hidden()).unwrap());
        assert_eq!(
            std::fs::read_to_string(dir.join(MARKER)).unwrap().trim(),
            "size=24 20 16 seed=2"
        );
        assert_ne!(std::fs::read(dir.join("seismic.strata")).unwrap(), first);
        assert!(!ensure_synthetic(&spec(&dir, 2), &ProgressBar::hidden()).unwrap());

        // An empty folder is generated into.
        let empty = root.path().join("empty");
        std::fs::create_dir(&empty).unwrap();
        assert!(ensure_synthetic(&spec(&empty, 2), &ProgressBar::hidden()).unwrap());
        assert!(empty.join(MARKER).is_file());
    }

    #[test]
    fn never_replaces_foreign_folders() {
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("precious");
        std::fs::create_dir(&dir).unwrap();
        std::fs::write(dir.join("thesis.tex"), "years of work").unwrap();
        let e = ensure_synthetic(&spec(&dir, 1), &ProgressBar::hidden()).unwrap_err();
        assert!(e.to_string().contains("thesis.tex"), "{e}");
        assert!(dir.join("thesis.tex").is_file());

        // A folder without the marker is not this cache's, even when its files have the
        // names a survey's have (`coordinator synth` output, a SEG-Y and text horizons).
        let survey = root.path().join("survey");
        std::fs::create_dir(&survey).unwrap();
        for n in [
            "seismic.sgy",
            "horizon_top.txt",
            "seismic.strata",
            "scene.toml",
        ] {
            std::fs::write(survey.join(n), "user data").unwrap();
        }
        let e = ensure_synthetic(&spec(&survey, 1), &ProgressBar::hidden()).unwrap_err();
        assert!(e.to_string().contains(MARKER), "{e}");
        for n in [
            "seismic.sgy",
            "horizon_top.txt",
            "seismic.strata",
            "scene.toml",
        ] {
            assert_eq!(std::fs::read(survey.join(n)).unwrap(), b"user data");
        }
        // A marked folder (another seed) that the user put a file of their own into.
        let marked = root.path().join("marked");
        assert!(ensure_synthetic(&spec(&marked, 1), &ProgressBar::hidden()).unwrap());
        std::fs::write(marked.join("seismic.sgy"), "user data").unwrap();
        let e = ensure_synthetic(&spec(&marked, 2), &ProgressBar::hidden()).unwrap_err();
        assert!(e.to_string().contains("seismic.sgy"), "{e}");
        assert!(marked.join("seismic.sgy").is_file());

        let file = root.path().join("plain");
        std::fs::write(&file, "x").unwrap();
        let e = ensure_synthetic(&spec(&file, 1), &ProgressBar::hidden()).unwrap_err();
        assert!(e.to_string().contains("not a folder"), "{e}");
    }

    #[test]
    fn failed_generation_leaves_nothing() {
        let root = tempfile::tempdir().unwrap();
        let mut s = spec(&root.path().join("demo"), 1);
        s.size = [4, 4, 4]; // too small for the model
        let e = ensure_synthetic(&s, &ProgressBar::hidden()).unwrap_err();
        assert!(format!("{e:#}").contains("demo"), "{e:#}");
        let names: Vec<String> = std::fs::read_dir(root.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["demo.lock"]);
    }
}
