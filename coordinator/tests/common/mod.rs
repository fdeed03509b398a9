//! Helpers the coordinator's end-to-end tests share: the binary, a synthetic survey per
//! test binary, EXR reading and image comparison, log cleaning.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

pub(crate) const BIN: &str = env!("CARGO_BIN_EXE_coordinator");
/// The image size of the survey renders.
pub(crate) const SIZE: &str = "96x64";

/// A small synthetic survey (cube + 3 horizons + scene.toml) in the target's temporary
/// folder under `name`, generated once per test binary.
pub(crate) fn survey_in(name: &str) -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(name);
        let out = Command::new(BIN)
            .args(["-q", "synth", "-o"])
            .arg(&dir)
            .args(["--size", "40", "32", "24", "--seed", "5"])
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        dir
    })
}

/// An EXR's RGBA pixels, row-major, for an image `w` pixels wide.
pub(crate) fn read_exr_sized(p: &Path, w: usize) -> Vec<[f32; 4]> {
    use exr::prelude::*;
    let img = read_first_rgba_layer_from_file(
        p,
        |res, _| vec![[0f32; 4]; res.width() * res.height()],
        move |px: &mut Vec<[f32; 4]>, pos, (r, g, b, a): (f32, f32, f32, f32)| {
            px[pos.y() * w + pos.x()] = [r, g, b, a];
        },
    )
    .unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    img.layer_data.channel_data.pixels
}

/// An EXR of the survey's size.
pub(crate) fn read_exr(p: &Path) -> Vec<[f32; 4]> {
    read_exr_sized(p, 96)
}

/// The largest difference of any channel of any pixel; infinite where either image holds a
/// NaN (a plain `f32::max` fold skips NaN).
pub(crate) fn max_diff(a: &[[f32; 4]], b: &[[f32; 4]]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .flat_map(|(p, q)| (0..4).map(move |c| (p[c] - q[c]).abs()))
        .fold(
            0.0,
            |m: f32, d: f32| if d.is_nan() { f32::INFINITY } else { m.max(d) },
        )
}

/// `s` without ANSI colour codes.
pub(crate) fn strip_ansi(s: &str) -> String {
    let mut out = String::new();
    let mut esc = false;
    for c in s.chars() {
        match (esc, c) {
            (false, '\u{1b}') => esc = true,
            (true, 'm') => esc = false,
            (true, _) => {}
            (false, c) => out.push(c),
        }
    }
    out
}
