//! Loading a scene file with command-line overrides (`--set KEY=VALUE`, `--size WxH`).
//!
//! `KEY` is a dotted path into the scene's TOML (`render.cache_mb`, `camera.fov_deg`,
//! `volume.0.opacity`): a numeric segment indexes an array (`[[volume]]` tables, or the
//! elements of `camera.eye`) from 0, and one outside it (negative, too large) is refused,
//! naming the array's length; missing intermediate tables are created. `VALUE` is read as a
//! TOML value (`x = VALUE`); text that is not one is taken as a string, so
//! `--set volume.0.colormap=grey` needs no quotes. The overridden table is then checked
//! against the scene model, and an error names the override that broke it; when that
//! override's value looked like TOML (an array, a table, a number, a quoted string) but did
//! not parse, the error says so and why, rather than only that a string does not fit.

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
    let mut scene = load_scene_as_written(path, sets, size)?;
    absolute_paths(&mut scene)?;
    Ok(scene)
}

/// Makes the scene's file paths (relative to the scene file, as parsed: relative to the
/// current folder when the scene's path is) absolute: the scene travels to workers, which
/// a launcher (`ssh host worker --connect ...`) may start in another folder.
fn absolute_paths(scene: &mut Scene) -> Result<()> {
    let mut paths: Vec<&mut std::path::PathBuf> = Vec::new();
    paths.extend(scene.volumes.iter_mut().map(|v| &mut v.store));
    paths.extend(scene.horizons.iter_mut().map(|h| &mut h.store));
    paths.extend(scene.synthetic.iter_mut().map(|s| &mut s.dir));
    paths.extend(scene.cluster.secret_file.iter_mut());
    paths.extend(scene.cluster.fingerprint_file.iter_mut());
    for p in paths {
        if p.is_relative() {
            *p = std::path::absolute(&*p)
                .with_context(|| format!("{}: cannot make the path absolute", p.display()))?;
        }
    }
    Ok(())
}

fn load_scene_as_written(path: &Path, sets: &[String], size: Option<(u32, u32)>) -> Result<Scene> {
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
            unparsed: None,
        });
        overrides.push(Override {
            label,
            key: "render.height".into(),
            value: Value::Integer(h.into()),
            unparsed: None,
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
    /// Why the value, which looked like TOML, did not parse as it (it was taken as a
    /// string).
    unparsed: Option<String>,
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
    let value = parse_value(raw);
    let unparsed = match value {
        Value::String(_) => why_not_toml(raw),
        _ => None,
    };
    Ok(Override {
        label,
        key: key.to_string(),
        value,
        unparsed,
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

/// Why `raw`, which starts as a TOML value other than a bare word does (`[`, `{`, a quote, a
/// digit, a sign or point before one), is not one: the parser's message on one line. `None`
/// for text that parses or does not look like TOML (`grey`, `radix-k`: plain strings).
/// Such text stays a string (`cluster.listen=[::1]:7000` is an address), but when the scene
/// refuses it the error can say it did not parse.
fn why_not_toml(raw: &str) -> Option<String> {
    let t = raw.trim();
    let mut chars = t.chars();
    let looks_like_toml = match (chars.next()?, chars.next()) {
        ('[' | '{' | '"' | '\'', _) => true,
        (c, _) if c.is_ascii_digit() => true,
        ('+' | '-' | '.', Some(d)) => d.is_ascii_digit(),
        _ => false,
    };
    if !looks_like_toml {
        return None;
    }
    const PREFIX: &str = "x = ";
    match format!("{PREFIX}{t}").parse::<Table>() {
        Err(e) => {
            let what = e
                .message()
                .lines()
                .map(str::trim)
                .filter(|l| !l.is_empty())
                .collect::<Vec<_>>()
                .join(": ");
            // Where in the value: the parser's messages alone ("expected newline") do not say.
            let rest = e
                .span()
                .and_then(|s| t.get(s.start.checked_sub(PREFIX.len())?..))
                .map(str::trim_end);
            Some(match rest {
                Some("") => format!("{what}, at the end"),
                Some(r) => format!("{what}, at `{r}`"),
                None => what,
            })
        }
        Ok(t) if t.len() != 1 => Some("it holds more than one value".into()),
        Ok(_) => None,
    }
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
                    if !matches!(seg_index(next), Index::NotANumber) {
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

/// A key segment read as an array index.
enum Index {
    /// A whole number that fits a `usize`.
    At(usize),
    /// A whole number no array reaches: negative, or beyond `usize`.
    Outside,
    /// Not a whole number.
    NotANumber,
}

/// Reads `seg` as an index. Negative and huge numbers are numbers too, so that they are
/// called out of range rather than "not a number" (or taken as a table's key).
fn seg_index(seg: &str) -> Index {
    let digits = seg.strip_prefix('-').unwrap_or(seg);
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return Index::NotANumber;
    }
    match seg.parse::<usize>() {
        Ok(i) => Index::At(i),
        Err(_) => Index::Outside,
    }
}

/// Checks an array index segment `seg` into the array `at` of `len` elements.
fn index(seg: &str, len: usize, at: &str) -> Result<usize> {
    match seg_index(seg) {
        Index::NotANumber => {
            bail!("{at} is an array: expected an index (a whole number from 0) instead of {seg:?}")
        }
        Index::At(i) if i < len => Ok(i),
        Index::At(_) | Index::Outside => Err(out_of_range(seg, len, at)),
    }
}

fn out_of_range(seg: &str, len: usize, at: &str) -> anyhow::Error {
    // Python's -1 counts from the end; here it is an error like any other.
    let negative = if seg.starts_with('-') {
        "; a negative index does not count from the end"
    } else {
        ""
    };
    anyhow::anyhow!(
        "index {seg} of {at} is out of range: the scene has {len} {at} entr{} (numbered from 0){negative}",
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
    // The error the final scene has, and the override from which on it has had it (an
    // earlier override may have broken the scene another way, which a later one fixed or
    // replaced: the error to report is the final one's).
    let message = |r: &Result<Scene, SceneError>| r.as_ref().err().map(|e| e.message.clone());
    let last = results.last().and_then(message);
    let culprit = last.as_ref().and_then(|last| {
        let from = (0..results.len())
            .rev()
            .take_while(|&k| message(&results[k]).as_ref() == Some(last))
            .last()?;
        (from > 0).then_some(from)
    });
    match culprit {
        Some(k) => {
            let o = &overrides[k - 1];
            let mut message = results[k]
                .as_ref()
                .err()
                .map_or_else(String::new, |e| e.message.clone());
            if let Some(why) = &o.unparsed {
                message = format!(
                    "the value did not parse as TOML ({why}) and was read as a string: {message}"
                );
            }
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

    /// Scene paths leave the coordinator absolute (workers may run in other folders).
    #[test]
    fn scene_paths_are_made_absolute() {
        let mut scene = Scene::parse(
            Path::new("configs/x.toml"),
            "[[volume]]\nstore = \"v.strata\"\n[synthetic]\ndir = \"s\"\nsize = [8, 8, 8]\n",
        )
        .unwrap();
        assert!(scene.volumes[0].store.is_relative());
        absolute_paths(&mut scene).unwrap();
        let here = std::env::current_dir().unwrap();
        assert_eq!(scene.volumes[0].store, here.join("configs/v.strata"));
        assert_eq!(scene.synthetic.unwrap().dir, here.join("configs/s"));
    }
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

        // The final scene's error is reported, blamed on the override from which on the
        // scene has had it: an earlier override's different error, which a later one
        // replaced, is not (it had been reported, though the final scene did not have it).
        // (The scene reports its render settings' errors before its layers'.)
        let e = load_scene(&p, &sets(&["volume.1.colormap=jet", "render.step=0"]), None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("after --set render.step=0"), "{e}");
        assert!(!e.contains("jet"), "{e}");
        // The same error from an earlier override on is blamed on that one.
        let e = load_scene(&p, &sets(&["render.step=0", "render.width=10"]), None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("after --set render.step=0"), "{e}");

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
    fn the_layer_checks_run_on_overridden_tables() {
        let (_d, p) = scene_file(SCENE);
        let e = load_scene(&p, &sets(&["volume.0.colormap=virdis"]), None)
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            format!(
                "{}: after --set volume.0.colormap=virdis: volume 0: colormap: unknown colour map \"virdis\" \
                 (expected one of seismic, bwr, grey, viridis, bone, hot, or one of them reversed as NAME_r) \
                 (key volume.0.colormap)",
                p.display()
            )
        );
        let e = load_scene(&p, &sets(&["volume.1.opacity=-1"]), None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("after --set volume.1.opacity=-1: volume 1: opacity -1 must be a finite number >= 0"),
            "{e}"
        );
        let e = load_scene(
            &p,
            &sets(&["volume.0.slices=[{ axis = \"time\", index = 1, opacity = 2 }]"]),
            None,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains(": volume 0: slice 0: opacity 2 must lie in 0..=1 (key volume.0.slices)"),
            "{e}"
        );
        let (_d, p) = scene_file("[[horizon]]\nstore = \"h.strata\"\n");
        let e = load_scene(&p, &sets(&["horizon.0.color_by=volume"]), None)
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            format!(
                "{}: after --set horizon.0.color_by=volume: horizon 0: volume 0 (read by color_by = \"volume\") \
                 names no [[volume]]: the scene has no [[volume]] (key horizon.0.color_by)",
                p.display()
            )
        );
        let e = load_scene(&p, &sets(&["horizon.0.color_by=height"]), None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("horizon 0: color_by \"height\" is unknown"),
            "{e}"
        );
        // A file that fails the checks on its own keeps its line and column.
        let (_d, p) = scene_file("[[volume]]\nstore = \"a\"\ncolormap = \"jet\"\n");
        let e = load_scene(&p, &sets(&["render.cache_mb=64"]), None)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with(&format!(
                "{}:3:1: volume 0: colormap: unknown colour map \"jet\"",
                p.display()
            )),
            "{e}"
        );
        assert!(e.ends_with("(with --set render.cache_mb=64)"), "{e}");
        // ... unless an override fixes it.
        let s = load_scene(&p, &sets(&["volume.0.colormap=bone"]), None).unwrap();
        assert_eq!(s.volumes[0].colormap, "bone");
    }

    #[test]
    fn negative_and_huge_indexes_are_out_of_range() {
        let (_d, p) = scene_file(SCENE);
        let err = |set: &str| format!("{:#}", load_scene(&p, &sets(&[set]), None).unwrap_err());
        assert_eq!(
            err("volume.-1.opacity=0.5"),
            format!(
                "{}: --set volume.-1.opacity=0.5: index -1 of volume is out of range: the scene has 2 volume \
                 entries (numbered from 0); a negative index does not count from the end",
                p.display()
            )
        );
        assert_eq!(
            err("volume.99999999999999999999.opacity=1"),
            format!(
                "{}: --set volume.99999999999999999999.opacity=1: index 99999999999999999999 of volume is out \
                 of range: the scene has 2 volume entries (numbered from 0)",
                p.display()
            )
        );
        // Into an array the file does not have: out of range too, not a table named "-1".
        let e = err("horizon.-1.opacity=1");
        assert!(
            e.contains("index -1 of horizon is out of range: the scene has 0 horizon entries"),
            "{e}"
        );
        let e = err("horizon.18446744073709551616.opacity=1");
        assert!(
            e.contains("index 18446744073709551616 of horizon is out of range"),
            "{e}"
        );
        // Arrays of values too.
        let e = format!(
            "{:#}",
            load_scene(
                &p,
                &sets(&["camera.eye=[1, 2, 3]", "camera.eye.-1=0"]),
                None
            )
            .unwrap_err()
        );
        assert!(
            e.contains(
                "--set camera.eye.-1=0: index -1 of camera.eye is out of range: the scene has 3"
            ),
            "{e}"
        );
        let e = err("volume.+1.opacity=1");
        assert!(
            e.contains(
                "volume is an array: expected an index (a whole number from 0) instead of \"+1\""
            ),
            "{e}"
        );
    }

    #[test]
    fn values_that_look_like_toml_but_do_not_parse_say_so() {
        for plain in [
            "grey",
            "radix-k",
            "[1, 2]",
            "\"quoted\"",
            "1.5",
            "-3",
            "{ a = 1 }",
            "",
        ] {
            assert_eq!(why_not_toml(plain), None, "{plain}");
        }
        for broken in [
            "[1, 2",
            "0,5",
            "{ a = 1",
            "\"grey",
            "1.5.",
            "-0,5",
            "[::1]:7000",
        ] {
            assert!(why_not_toml(broken).is_some(), "{broken}");
        }
        let (_d, p) = scene_file(SCENE);
        let e = load_scene(&p, &sets(&["camera.eye=[1, 2"]), None)
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            format!(
                "{}: after --set camera.eye=[1, 2: the value did not parse as TOML (invalid array: \
                 expected `]`, at the end) and was read as a string: invalid type: string \"[1, 2\", \
                 expected an array of length 3 (key camera.eye)",
                p.display()
            )
        );
        let e = load_scene(&p, &sets(&["volume.0.opacity=0,5"]), None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(
                "after --set volume.0.opacity=0,5: the value did not parse as TOML (expected newline, \
                 `#`, at `,5`) and was read as a string: invalid type: string \"0,5\", expected f64"
            ),
            "{e}"
        );
        // Text that is a string where the scene wants one stays one.
        let s = load_scene(&p, &sets(&["cluster.listen=[::1]:7000"]), None).unwrap();
        assert_eq!(s.cluster.listen, "[::1]:7000");
        // A plain word that does not fit says only that (it never looked like TOML).
        let e = load_scene(&p, &sets(&["volume.0.opacity=half"]), None)
            .unwrap_err()
            .to_string();
        assert!(!e.contains("did not parse"), "{e}");
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
