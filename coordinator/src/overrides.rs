//! Loading a scene file with command-line overrides (`--set KEY=VALUE`, `--size WxH`).
//!
//! `KEY` is a dotted path into the scene's TOML (`render.cache_mb`, `camera.fov_deg`,
//! `volume.0.opacity`): a numeric segment indexes an array (`[[volume]]` tables, or the
//! elements of `camera.eye`), missing intermediate tables are created. `VALUE` is read as a
//! TOML value (`x = VALUE`); text that is not one is taken as a string, so
//! `--set volume.0.colormap=grey` needs no quotes. The overridden table is then checked
//! against the scene model, and an error names the override that broke it.

use anyhow::{bail, Context, Result};
use std::path::Path;
use strata_common::scene::{line_col, Scene, SceneError};
use toml::{Table, Value};

/// Largest image side `parse_size` accepts.
pub const MAX_SIDE: u32 = strata_common::scene::MAX_IMAGE_SIDE;

/// Reads the scene file at `path`, applies the `KEY=VALUE` overrides in `sets` in order and
/// then `size` (`render.width`, `render.height`), and parses the result.
///
/// Without overrides this is `Scene::parse` (errors say `file:line:col: message`). With
/// overrides, syntax errors of the file still say `file:line:col`, and an override that
/// makes the scene invalid is named: `scene.toml: after --set render.cache_mb=abc: invalid
/// type: string "abc", expected u64 (key render.cache_mb)`.
pub fn load_scene(path: &Path, sets: &[String], size: Option<(u32, u32)>) -> Result<Scene> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read the scene", path.display()))?;
    if sets.is_empty() && size.is_none() {
        return Ok(Scene::parse(path, &text)?);
    }
    let table: Table = text.parse().map_err(|e: toml::de::Error| {
        let (line, column) = e.span().map_or((1, 1), |s| line_col(&text, s.start));
        SceneError {
            path: path.to_path_buf(),
            line,
            column,
            message: e.message().to_string(),
        }
    })?;

    let mut overrides = Vec::with_capacity(sets.len() + 2);
    for s in sets {
        overrides.push(parse_set(s)?);
    }
    if let Some((w, h)) = size {
        let label = format!("--size {w}x{h}");
        overrides.push(Override {
            label: label.clone(),
            key: "render.width".into(),
            value: Value::Integer(w.into()),
        });
        overrides.push(Override {
            label,
            key: "render.height".into(),
            value: Value::Integer(h.into()),
        });
    }

    // Apply all overrides, keeping each intermediate table for error attribution.
    let mut stages = Vec::with_capacity(overrides.len() + 1);
    stages.push(table);
    for o in &overrides {
        let mut next = stages.last().expect("the file's table").clone();
        set_path(&mut next, &o.key, o.value.clone())
            .with_context(|| format!("{}: {}", path.display(), o.label))?;
        stages.push(next);
    }
    let last = stages.last().expect("the file's table");
    match Scene::parse(path, &last.to_string()) {
        Ok(scene) => Ok(scene),
        Err(_) => Err(explain_failure(path, &text, &stages, &overrides)),
    }
}

/// Parses `WIDTHxHEIGHT` (`1920x1080`; `X` and `*` also separate), each side 1..=32768.
pub fn parse_size(s: &str) -> Result<(u32, u32)> {
    let t = s.trim();
    let (w, h) = t
        .split_once(['x', 'X', '*'])
        .with_context(|| format!("size {s:?}: expected WIDTHxHEIGHT, e.g. 1920x1080"))?;
    let side = |v: &str, what: &str| -> Result<u32> {
        let n: u64 = v.trim().parse().with_context(|| {
            format!("size {s:?}: {what} {v:?} is not a whole number (expected WIDTHxHEIGHT, e.g. 1920x1080)")
        })?;
        anyhow::ensure!(n > 0, "size {s:?}: the {what} must be at least 1");
        anyhow::ensure!(
            n <= u64::from(MAX_SIDE),
            "size {s:?}: the {what} {n} is above the limit of {MAX_SIDE} pixels"
        );
        Ok(n as u32)
    };
    Ok((side(w, "width")?, side(h, "height")?))
}

/// One override: what the user wrote, the dotted key, the value.
#[derive(Debug)]
struct Override {
    label: String,
    key: String,
    value: Value,
}

/// Parses `KEY=VALUE` (VALUE as TOML, else as a string).
fn parse_set(s: &str) -> Result<Override> {
    let label = format!("--set {s}");
    let Some((key, raw)) = s.split_once('=') else {
        bail!("{label}: expected KEY=VALUE, e.g. render.cache_mb=2048");
    };
    let key = key.trim();
    if key.is_empty() {
        bail!("{label}: the key is empty (expected KEY=VALUE, e.g. render.cache_mb=2048)");
    }
    if key.split('.').any(|seg| seg.trim().is_empty()) {
        bail!("{label}: the key {key:?} has an empty segment");
    }
    Ok(Override {
        label,
        key: key.to_string(),
        value: parse_value(raw),
    })
}

/// A TOML value if `raw` is one (`x = RAW` parses to exactly one key), else the trimmed
/// string.
fn parse_value(raw: &str) -> Value {
    let trimmed = raw.trim();
    if !trimmed.is_empty() {
        if let Ok(mut t) = format!("x = {trimmed}").parse::<Table>() {
            if t.len() == 1 {
                if let Some(v) = t.remove("x") {
                    return v;
                }
            }
        }
    }
    Value::String(trimmed.to_string())
}

/// Sets the dotted `key` in `table` to `value`.
fn set_path(table: &mut Table, key: &str, value: Value) -> Result<()> {
    let segs: Vec<&str> = key.split('.').map(str::trim).collect();
    // Work on the table as a value; `set_in` never replaces the root itself.
    let mut root = Value::Table(std::mem::take(table));
    let result = set_in(&mut root, &segs, value);
    if let Value::Table(t) = root {
        *table = t;
    }
    result
}

/// Walks `segs` down from `root`, creating missing tables, and sets the last one.
fn set_in(root: &mut Value, segs: &[&str], value: Value) -> Result<()> {
    let (last, parents) = segs.split_last().context("empty key")?;
    let mut cur = root;
    let mut at = String::new();
    for (n, seg) in parents.iter().enumerate() {
        cur = match cur {
            Value::Table(t) => {
                if !t.contains_key(*seg) {
                    let next = segs[n + 1];
                    if seg_index(next).is_some() {
                        // `volume.0.x` with no `volume`: an index into nothing.
                        let mut here = at.clone();
                        push_seg(&mut here, seg);
                        return Err(out_of_range(next, 0, &here));
                    }
                    t.insert((*seg).to_string(), Value::Table(Table::new()));
                }
                t.get_mut(*seg).expect("just inserted")
            }
            Value::Array(a) => {
                let i = index(seg, a.len(), &at)?;
                &mut a[i]
            }
            _ => bail!("{} is not a table, so it has no key {seg}", name(&at)),
        };
        push_seg(&mut at, seg);
    }
    match cur {
        Value::Table(t) => {
            t.insert((*last).to_string(), value);
        }
        Value::Array(a) => {
            let i = index(last, a.len(), &at)?;
            a[i] = value;
        }
        _ => bail!("{} is not a table, so it has no key {last}", name(&at)),
    }
    Ok(())
}

fn name(at: &str) -> &str {
    if at.is_empty() {
        "the scene"
    } else {
        at
    }
}

fn seg_index(seg: &str) -> Option<usize> {
    if seg.bytes().all(|b| b.is_ascii_digit()) {
        seg.parse().ok()
    } else {
        None
    }
}

/// Checks an array index segment `seg` into the array `at` of `len` elements.
fn index(seg: &str, len: usize, at: &str) -> Result<usize> {
    match seg_index(seg) {
        None => bail!("{at} is an array: expected a number instead of {seg:?}"),
        Some(i) if i >= len => Err(out_of_range(seg, len, at)),
        Some(i) => Ok(i),
    }
}

fn out_of_range(seg: &str, len: usize, at: &str) -> anyhow::Error {
    anyhow::anyhow!(
        "index {seg} of {at} is out of range: the scene has {len} {at} entr{} (numbered from 0)",
        if len == 1 { "y" } else { "ies" }
    )
}

fn push_seg(at: &mut String, seg: &str) {
    if !at.is_empty() {
        at.push('.');
    }
    at.push_str(seg);
}

/// The error for an overridden scene that does not parse: the last override that turned a
/// valid scene into an invalid one, or the file's own error if it never was valid.
fn explain_failure(
    path: &Path,
    text: &str,
    stages: &[Table],
    overrides: &[Override],
) -> anyhow::Error {
    let results: Vec<Result<Scene, SceneError>> = stages
        .iter()
        .map(|t| Scene::parse(path, &t.to_string()))
        .collect();
    let culprit = (1..results.len())
        .rev()
        .find(|&k| results[k - 1].is_ok() && results[k].is_err());
    match culprit {
        Some(k) => {
            let o = &overrides[k - 1];
            let message = results[k]
                .as_ref()
                .err()
                .map_or_else(String::new, |e| e.message.clone());
            anyhow::anyhow!(
                "{}: after {}: {message} (key {})",
                path.display(),
                o.label,
                o.key
            )
        }
        // The file is invalid on its own (and the overrides did not fix it): report the
        // file's own error with its line and column.
        None => match Scene::parse(path, text) {
            Err(e) => anyhow::anyhow!(
                "{e} (with {})",
                overrides
                    .iter()
                    .map(|o| o.label.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
            Ok(_) => anyhow::anyhow!("{}: the overridden scene is invalid", path.display()),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    const SCENE: &str = "# test scene\n[[volume]]\nstore = \"cube.strata\"\n\n[[volume]]\nstore = \"ct.strata\"\ncolormap = \"grey\"\n\n[render]\nwidth = 64\nheight = 48\n";

    fn scene_file(text: &str) -> (tempfile::TempDir, PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("scene.toml");
        std::fs::write(&p, text).unwrap();
        (dir, p)
    }

    fn sets(s: &[&str]) -> Vec<String> {
        s.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn no_overrides_is_scene_parse() {
        let (_d, p) = scene_file(SCENE);
        let s = load_scene(&p, &[], None).unwrap();
        assert_eq!(s, Scene::parse(&p, SCENE).unwrap());
        assert_eq!(s.volumes[0].store, p.parent().unwrap().join("cube.strata"));

        let (_d, p) = scene_file("[render]\nwidth = 64\nheigth = 3\n");
        let e = load_scene(&p, &[], None).unwrap_err().to_string();
        assert!(e.starts_with(&format!("{}:3:1:", p.display())), "{e}");

        let e = load_scene(Path::new("/no/such/scene.toml"), &[], None).unwrap_err();
        assert!(e.to_string().contains("/no/such/scene.toml"), "{e}");
    }

    #[test]
    fn applies_overrides() {
        let (_d, p) = scene_file(SCENE);
        let s = load_scene(
            &p,
            &sets(&[
                "render.cache_mb=2048",
                "render.z_scale=4",
                "render.lighting=false",
                "camera.eye=[1.0, 2.0, 3.0]",
                "camera.target=[0, 0, 0]",
                "camera.fov_deg=50",
                "camera.eye.2=7.5",
                "volume.1.opacity=0.25",
                "volume.0.colormap=grey",
                "volume.0.window=[-1.0, 1.0]",
                "render.background = [0.1, 0.1, 0.1]",
            ]),
            Some((1920, 1080)),
        )
        .unwrap();
        assert_eq!(s.render.cache_mb, 2048);
        assert_eq!(s.render.z_scale, 4.0);
        assert!(!s.render.lighting);
        assert_eq!((s.render.width, s.render.height), (1920, 1080));
        assert_eq!(s.render.background, [0.1; 3]);
        let cam = s.camera.unwrap();
        assert_eq!(cam.eye, [1.0, 2.0, 7.5]);
        assert_eq!(cam.fov_deg, 50.0);
        assert_eq!(s.volumes[1].opacity, 0.25);
        assert_eq!(s.volumes[1].colormap, "grey");
        assert_eq!(s.volumes[0].colormap, "grey");
        assert_eq!(s.volumes[0].window, Some([-1.0, 1.0]));
        // Store paths still resolve against the scene file.
        assert_eq!(s.volumes[1].store, p.parent().unwrap().join("ct.strata"));

        // --size wins over --set of the same keys.
        let s = load_scene(&p, &sets(&["render.width=10"]), Some((30, 20))).unwrap();
        assert_eq!((s.render.width, s.render.height), (30, 20));
        // Later --set wins over earlier ones; --size alone is an override too.
        let s = load_scene(&p, &sets(&["render.step=2", "render.step=0.5"]), None).unwrap();
        assert_eq!(s.render.step, 0.5);
        let s = load_scene(&p, &[], Some((8, 9))).unwrap();
        assert_eq!((s.render.width, s.render.height), (8, 9));

        // The re-split's clock: CPU time unless asked otherwise; an unknown one is named.
        use strata_common::scene::RebalanceClock;
        assert_eq!(s.cluster.rebalance_clock, RebalanceClock::Cpu);
        let s = load_scene(&p, &sets(&["cluster.rebalance_clock=wall"]), None).unwrap();
        assert_eq!(s.cluster.rebalance_clock, RebalanceClock::Wall);
        let e = load_scene(&p, &sets(&["cluster.rebalance_clock=gpu"]), None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("cluster.rebalance_clock") && e.contains("expected `cpu` or `wall`"),
            "{e}"
        );
    }

    #[test]
    fn values_fall_back_to_strings() {
        assert_eq!(parse_value("grey"), Value::String("grey".into()));
        assert_eq!(parse_value(" grey "), Value::String("grey".into()));
        assert_eq!(parse_value("radix-k"), Value::String("radix-k".into()));
        assert_eq!(parse_value("\"quoted\""), Value::String("quoted".into()));
        assert_eq!(parse_value("12"), Value::Integer(12));
        assert_eq!(parse_value("1.5"), Value::Float(1.5));
        assert_eq!(parse_value("true"), Value::Boolean(true));
        assert_eq!(parse_value(""), Value::String(String::new()));
        // Something that would smuggle in a second key stays a string.
        assert_eq!(parse_value("1\ny = 2"), Value::String("1\ny = 2".into()));
    }

    #[test]
    fn invalid_override_names_the_key() {
        let (_d, p) = scene_file(SCENE);
        let e = load_scene(&p, &sets(&["render.cache_mb=abc"]), None)
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            format!(
                "{}: after --set render.cache_mb=abc: invalid type: string \"abc\", expected u64 (key render.cache_mb)",
                p.display()
            )
        );

        // Unknown keys are rejected (deny_unknown_fields), naming the key.
        let e = load_scene(&p, &sets(&["render.cache_mb=5", "render.cach_mb=5"]), None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("after --set render.cach_mb=5"), "{e}");
        assert!(e.contains("cach_mb"), "{e}");
        assert!(e.contains("(key render.cach_mb)"), "{e}");
        let e = load_scene(&p, &sets(&["composite.algoritm=radix-k"]), None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("unknown field `algoritm`"), "{e}");
        assert!(e.contains("(key composite.algoritm)"), "{e}");
        let e = load_scene(&p, &sets(&["volume.0.colour=grey"]), None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("unknown field `colour`"), "{e}");
        assert!(e.contains("(key volume.0.colour)"), "{e}");
    }

    #[test]
    fn structural_errors_name_the_override() {
        let (_d, p) = scene_file(SCENE);
        let e = format!(
            "{:#}",
            load_scene(&p, &sets(&["volume.2.opacity=1"]), None).unwrap_err()
        );
        assert!(e.contains("--set volume.2.opacity=1"), "{e}");
        assert!(e.contains("index 2 of volume is out of range"), "{e}");
        let e = format!(
            "{:#}",
            load_scene(&p, &sets(&["horizon.0.opacity=1"]), None).unwrap_err()
        );
        // No [[horizon]] in the file: index 0 into nothing.
        assert!(e.contains("--set horizon.0.opacity=1"), "{e}");
        assert!(
            e.contains("index 0 of horizon is out of range: the scene has 0 horizon entries"),
            "{e}"
        );
        let e = format!(
            "{:#}",
            load_scene(&p, &sets(&["volume.first.opacity=1"]), None).unwrap_err()
        );
        assert!(e.contains("volume is an array"), "{e}");
        let e = format!(
            "{:#}",
            load_scene(&p, &sets(&["render.width.x=1"]), None).unwrap_err()
        );
        assert!(e.contains("render.width is not a table"), "{e}");

        for bad in ["render.width", "=3", " =3", "render..width=3", "render.=3"] {
            let e = load_scene(&p, &sets(&[bad]), None).unwrap_err().to_string();
            assert!(e.contains(&format!("--set {bad}")), "{e}");
        }
    }

    #[test]
    fn syntax_errors_keep_line_and_column() {
        let (_d, p) = scene_file("[render]\nwidth = 64\nheight = = 3\n");
        let e = load_scene(&p, &sets(&["render.cache_mb=1"]), None)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with(&format!("{}:3:", p.display())), "{e}");

        // A file that is valid TOML but not a valid scene: its own error, with position.
        let (_d, p) = scene_file("[render]\nwidth = 64\nheigth = 3\n");
        let e = load_scene(&p, &sets(&["render.cache_mb=1"]), None)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with(&format!("{}:3:1:", p.display())), "{e}");
        assert!(e.contains("heigth"), "{e}");
        // ... unless an override fixes it.
        let (_d, p) = scene_file("[render]\nwidth = \"wide\"\n");
        let s = load_scene(&p, &sets(&["render.width=5"]), None).unwrap();
        assert_eq!(s.render.width, 5);
    }

    #[test]
    fn sizes() {
        assert_eq!(parse_size("1920x1080").unwrap(), (1920, 1080));
        assert_eq!(parse_size("64X48").unwrap(), (64, 48));
        assert_eq!(parse_size("8*9").unwrap(), (8, 9));
        assert_eq!(parse_size(" 32768x1 ").unwrap(), (32768, 1));
        for bad in [
            "", "1920", "x1080", "1920x", "0x10", "10x0", "32769x10", "-5x5", "axb", "1x2x3",
        ] {
            let e = parse_size(bad).unwrap_err().to_string();
            assert!(e.contains(&format!("{bad:?}")), "{e}");
        }
        assert!(parse_size("0x10")
            .unwrap_err()
            .to_string()
            .contains("at least 1"));
        assert!(parse_size("40000x10")
            .unwrap_err()
            .to_string()
            .contains("32768"));
    }

    #[test]
    fn demo_scene_parses() {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/demo.toml");
        let s = load_scene(&p, &[], None).unwrap();
        let syn = s.synthetic.as_ref().unwrap();
        assert_eq!(syn.size, [600, 400, 300]);
        assert_eq!(syn.seed, 7);
        assert!(syn.dir.ends_with("synthetic/demo"));
        assert_eq!(s.volumes.len(), 1);
        assert_eq!(s.horizons.len(), 3);
        // The geoscientist's view: inline, crossline and time slices.
        let axes: Vec<_> = s.volumes[0].slices.iter().map(|x| x.axis).collect();
        use strata_common::scene::SliceAxis::*;
        assert_eq!(axes, [Inline, Crossline, Time]);
        assert!(s.volumes[0].store.starts_with(&syn.dir));
        for h in &s.horizons {
            assert!(h.store.starts_with(&syn.dir));
        }
        assert_eq!((s.render.width, s.render.height), (1280, 720));
        assert_eq!(s.render.z_scale, 4.0);
        assert!(s.camera.is_some());
        // Every render key is written out, at its default apart from the noted ones.
        let defaults = strata_common::scene::RenderSettings {
            z_scale: 4.0,
            ..Default::default()
        };
        assert_eq!(s.render, defaults);
        let text = std::fs::read_to_string(&p).unwrap();
        let table: Table = text.parse().unwrap();
        let render = table["render"].as_table().unwrap();
        let all: Table = toml::from_str(&toml::to_string(&defaults).unwrap()).unwrap();
        for k in all.keys() {
            assert!(
                render.contains_key(k),
                "configs/demo.toml: render.{k} is not written out"
            );
        }
        // So are the composite and cluster keys (secret and fingerprint files are optional).
        assert_eq!(s.composite, Default::default());
        assert_eq!(s.cluster, Default::default());
        for (section, value) in [
            ("composite", toml::to_string(&s.composite).unwrap()),
            ("cluster", toml::to_string(&s.cluster).unwrap()),
        ] {
            let written = table[section].as_table().unwrap();
            let all: Table = toml::from_str(&value).unwrap();
            for k in all.keys() {
                assert!(
                    written.contains_key(k),
                    "configs/demo.toml: {section}.{k} is not written out"
                );
            }
        }
        // And overrides apply to it, including the compositing keys.
        let s = load_scene(
            &p,
            &sets(&[
                "composite.algorithm=binary-swap",
                "composite.k=[4, 2]",
                "composite.wire=f16",
            ]),
            None,
        )
        .unwrap();
        assert_eq!(
            s.composite.algorithm,
            strata_common::composite::Algorithm::BinarySwap
        );
        assert_eq!(
            s.composite.k,
            strata_common::scene::KSetting::Factors(vec![4, 2])
        );
        assert_eq!(s.composite.wire, strata_common::composite::WireFormat::F16);
        let e = load_scene(&p, &sets(&["composite.algorithm=tree"]), None).unwrap_err();
        assert!(format!("{e:#}").contains("composite.algorithm"), "{e:#}");
        let s = load_scene(&p, &sets(&["render.cache_mb=64"]), Some((320, 200))).unwrap();
        assert_eq!(s.render.cache_mb, 64);
        assert_eq!((s.render.width, s.render.height), (320, 200));
    }
}
