//! Frame sequences: the output paths of numbered frames.
//!
//! A `printf`-style `%d` or `%0Nd` (e.g. `frame_%05d.png`) in an output path is replaced by
//! the frame number, as ffmpeg and most render farms expect. `%%` stands for a literal `%`.

use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};
use std::process::Command;

/// Where the frame-number pattern sits in a path: byte range and zero-padded width.
struct Pattern {
    start: usize,
    end: usize,
    width: usize,
}

fn find(s: &str) -> Result<Option<Pattern>> {
    let b = s.as_bytes();
    let mut found = None;
    let mut i = 0;
    while i < b.len() {
        if b[i] != b'%' {
            i += 1;
            continue;
        }
        if b.get(i + 1) == Some(&b'%') {
            i += 2;
            continue;
        }
        let mut j = i + 1;
        while j < b.len() && b[j].is_ascii_digit() {
            j += 1;
        }
        if b.get(j) != Some(&b'd') {
            bail!("{s:?}: '%' at byte {i} must start %d or %0Nd (or be doubled, %%)");
        }
        let digits = &s[i + 1..j];
        if !digits.is_empty() && !digits.starts_with('0') {
            bail!("{s:?}: frame numbers are zero-padded (%0{digits}d), not {digits} wide");
        }
        let width: usize = if digits.is_empty() {
            0
        } else {
            digits.parse().context("pattern width")?
        };
        if width > 12 {
            bail!("{s:?}: a frame-number width of {width} is more than 12 digits");
        }
        if found.is_some() {
            bail!("{s:?}: more than one frame-number pattern");
        }
        found = Some(Pattern {
            start: i,
            end: j + 1,
            width,
        });
        i = j + 1;
    }
    Ok(found)
}

/// Whether the path holds a frame-number pattern (and is otherwise well formed).
pub fn is_numbered(template: &Path) -> Result<bool> {
    let s = template
        .to_str()
        .with_context(|| format!("{}: not UTF-8", template.display()))?;
    Ok(find(s)?.is_some())
}

/// The path of frame `frame`: the pattern replaced by the zero-padded number, `%%` by `%`.
pub fn numbered(template: &Path, frame: u32) -> Result<PathBuf> {
    let s = template
        .to_str()
        .with_context(|| format!("{}: not UTF-8", template.display()))?;
    let p = find(s)?
        .with_context(|| format!("{s:?} has no frame-number pattern such as frame_%05d.png"))?;
    let unescape = |t: &str| t.replace("%%", "%");
    Ok(PathBuf::from(format!(
        "{}{:0width$}{}",
        unescape(&s[..p.start]),
        frame,
        unescape(&s[p.end..]),
        width = p.width
    )))
}

/// Whether `path` is one of the frame paths of `template` (some frame number, at least as
/// wide as the pattern's padding), compared as strings. `false` for a template without a
/// pattern.
pub fn is_frame_of(template: &Path, path: &Path) -> bool {
    let (Some(t), Some(s)) = (template.to_str(), path.to_str()) else {
        return false;
    };
    let Ok(Some(p)) = find(t) else {
        return false;
    };
    let unescape = |t: &str| t.replace("%%", "%");
    let (head, tail) = (unescape(&t[..p.start]), unescape(&t[p.end..]));
    let Some(digits) = s
        .strip_prefix(head.as_str())
        .and_then(|r| r.strip_suffix(tail.as_str()))
    else {
        return false;
    };
    !digits.is_empty()
        && digits.len() >= p.width.max(1)
        && digits.bytes().all(|b| b.is_ascii_digit())
        && (digits.len() == p.width || !digits.starts_with('0') || digits.len() == 1)
}

/// What became of an MP4 request.
#[derive(Debug, PartialEq, Eq)]
pub enum Mp4 {
    /// Written.
    Written,
    /// `ffmpeg` is not on the PATH; the frames stand alone.
    NoFfmpeg,
}

/// Encodes the `count` numbered PNG frames `first..first + count` of `pattern` into an
/// H.264 MP4 at `fps`, with `ffmpeg` from the PATH (never required: without it nothing is
/// written and [`Mp4::NoFfmpeg`] says so). An odd width or height is padded by one black
/// row or column (H.264's 4:2:0 needs even sides). The file appears atomically: ffmpeg
/// writes a temporary file beside it, renamed when it succeeds.
pub fn encode_mp4(pattern: &Path, first: u32, count: u32, fps: f64, out: &Path) -> Result<Mp4> {
    anyhow::ensure!(count > 0, "no frames to encode into {}", out.display());
    anyhow::ensure!(
        fps > 0.0 && fps.is_finite(),
        "MP4 frame rate must be positive, got {fps}"
    );
    let dir = out.parent().filter(|p| !p.as_os_str().is_empty());
    let name = out
        .file_name()
        .with_context(|| format!("{}: not a file name", out.display()))?
        .to_string_lossy()
        .into_owned();
    let tmp = dir
        .map_or_else(PathBuf::new, Path::to_path_buf)
        .join(format!(".{name}.partial.mp4"));
    let run = Command::new("ffmpeg")
        // (The cluster's secret may be in this process's environment: not for ffmpeg.)
        .env_remove(strata_net::secret::SECRET_ENV)
        .args(["-y", "-loglevel", "error", "-framerate"])
        .arg(format!("{fps}"))
        .args(["-start_number", &first.to_string(), "-i"])
        .arg(pattern)
        .args(["-frames:v", &count.to_string()])
        .args([
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2",
            "-c:v",
            "libx264",
            "-pix_fmt",
            "yuv420p",
            "-movflags",
            "+faststart",
        ])
        .arg(&tmp)
        .output();
    let o = match run {
        Ok(o) => o,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Mp4::NoFfmpeg),
        Err(e) => return Err(e).context("running ffmpeg"),
    };
    if !o.status.success() || !tmp.is_file() {
        let _ = std::fs::remove_file(&tmp);
        let err = String::from_utf8_lossy(&o.stderr);
        let tail: Vec<&str> = err.lines().rev().take(5).collect();
        bail!(
            "ffmpeg could not encode {} into {} ({}): {}",
            pattern.display(),
            out.display(),
            o.status,
            tail.into_iter().rev().collect::<Vec<_>>().join(" | ")
        );
    }
    std::fs::rename(&tmp, out).with_context(|| format!("writing {}", out.display()))?;
    Ok(Mp4::Written)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patterns_number_frames() {
        let n = |t: &str, f| numbered(Path::new(t), f).unwrap();
        assert_eq!(
            n("out/frame_%05d.png", 42),
            Path::new("out/frame_00042.png")
        );
        assert_eq!(n("f%d.exr", 7), Path::new("f7.exr"));
        assert_eq!(n("f%03d.png", 12345), Path::new("f12345.png"));
        assert_eq!(n("100%%_%04d.png", 3), Path::new("100%_0003.png"));
        assert!(is_numbered(Path::new("a_%05d.png")).unwrap());
        assert!(!is_numbered(Path::new("a.png")).unwrap());
        assert!(!is_numbered(Path::new("100%%.png")).unwrap());
    }

    #[test]
    fn frame_paths_are_recognised_as_the_patterns_frames() {
        let of = |t: &str, p: &str| is_frame_of(Path::new(t), Path::new(p));
        // Every path `numbered` makes is a frame of its pattern.
        for t in ["out/f_%03d.png", "f%d.exr", "100%%_%04d.png"] {
            for f in [0, 1, 7, 42, 999, 1000, 12345] {
                let p = numbered(Path::new(t), f).unwrap();
                assert!(is_frame_of(Path::new(t), &p), "{t} {}", p.display());
            }
        }
        assert!(
            !of("out/f_%03d.png", "out/f_01.png"),
            "narrower than the padding"
        );
        assert!(
            !of("out/f_%03d.png", "out/f_0001.png"),
            "padded past the width"
        );
        assert!(!of("f%d.exr", "f012.exr"));
        assert!(!of("out/f_%03d.png", "out/f_001.mp4"));
        assert!(!of("out/f_%03d.png", "out/f_.png"));
        assert!(!of("out/f_%03d.png", "out/f_00x.png"));
        assert!(!of("out/f_%03d.png", "other/f_001.png"));
        assert!(!of("out/f.png", "out/f.png"), "no pattern, no frames");
    }

    #[test]
    fn bad_patterns_are_refused() {
        for bad in [
            "a_%5d.png",
            "a_%s.png",
            "a_%05d_%05d.png",
            "a_%099d.png",
            "a_%",
        ] {
            assert!(is_numbered(Path::new(bad)).is_err(), "{bad}");
        }
        let e = numbered(Path::new("plain.png"), 1).unwrap_err();
        assert!(format!("{e}").contains("frame_%05d"), "{e}");
    }
}
