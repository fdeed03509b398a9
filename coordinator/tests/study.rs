//! `coordinator study accuracy` end to end on a small synthetic survey: every knob
//! measured, errors that behave as the knobs say they must, and the report, table and plots
//! written.

use std::path::Path;
use std::process::Command;

mod common;
use common::BIN;

struct Row {
    knob: String,
    label: String,
    seconds: f64,
    samples: u64,
    rmse: f64,
    max: f64,
    dssim: f64,
    note: String,
}

fn rows(csv_path: &Path) -> Vec<Row> {
    let mut r = csv::Reader::from_path(csv_path).unwrap();
    r.records()
        .map(|rec| {
            let rec = rec.unwrap();
            Row {
                knob: rec[0].to_string(),
                label: rec[1].to_string(),
                seconds: rec[3].parse().unwrap(),
                samples: rec[4].parse().unwrap(),
                rmse: rec[5].parse().unwrap(),
                max: rec[6].parse().unwrap(),
                dssim: rec[7].parse().unwrap(),
                note: rec[9].to_string(),
            }
        })
        .collect()
}

#[test]
fn accuracy_study_of_a_small_survey() {
    let tmp = tempfile::tempdir().unwrap();
    let survey = common::survey_in("study-survey");
    let dir = tmp.path().join("study");
    let out = Command::new(BIN)
        .args(["-q", "study", "accuracy"])
        .arg(survey.join("scene.toml"))
        .arg("-o")
        .arg(&dir)
        .args([
            "--size",
            "48x32",
            "--frames",
            "1",
            "--workers",
            "2",
            "--no-gpu",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    let rows = rows(&dir.join("points.csv"));
    assert_eq!(rows[0].knob, "reference");
    assert_eq!(rows[0].rmse, 0.0);
    assert_eq!(rows[1].knob, "defaults");
    let get = |knob: &str, label: &str| {
        rows.iter()
            .find(|r| r.knob == knob && r.label.starts_with(label))
            .unwrap_or_else(|| panic!("no point {knob} {label}"))
    };
    for r in &rows[1..] {
        assert!(
            r.note.is_empty() || !r.note.starts_with("skipped"),
            "{} {}: {}",
            r.knob,
            r.label,
            r.note
        );
        assert!(r.seconds > 0.0 && r.samples > 0, "{} {}", r.knob, r.label);
        assert!(r.rmse.is_finite() && r.rmse <= r.max && r.max <= 1.0);
        assert!(
            (0.0..=2.0).contains(&r.dssim),
            "{} {}: {}",
            r.knob,
            r.label,
            r.dssim
        );
    }
    // The reference takes 16 × the samples per ray: the defaults take far fewer.
    assert!(rows[0].samples > 4 * rows[1].samples);
    // A finer step is closer to the reference than a coarser one, and not free.
    let (fine, coarse) = (get("step", "step 0.25"), get("step", "step 4"));
    assert!(fine.rmse < coarse.rmse, "{} vs {}", fine.rmse, coarse.rmse);
    assert!(fine.samples > coarse.samples);
    // No early termination is closer than stopping at 90 %.
    assert!(get("early-termination", "ERT 1").rmse <= get("early-termination", "ERT 0.9").rmse);
    // The other knobs were all measured.
    for knob in [
        "tau",
        "adaptive-step",
        "coarsening-filter",
        "wire-precision",
        "backend",
        "preintegrated",
        "step+preintegrated",
        "step+tau",
        "step+early-termination",
    ] {
        assert!(rows.iter().any(|r| r.knob == knob), "no {knob} point");
    }
    // f16 on the wire rounds each channel to 11 significant bits: the distributed image
    // moves by at most that, so its error against the reference does too.
    let (w32, w16) = (
        get("wire-precision", "2 workers, f32"),
        get("wire-precision", "2 workers, f16"),
    );
    assert!(
        (w16.rmse - w32.rmse).abs() < 2e-3,
        "{} vs {}",
        w16.rmse,
        w32.rmse
    );
    assert!(
        (w16.max - w32.max).abs() < 4e-3,
        "{} vs {}",
        w16.max,
        w32.max
    );

    let report = std::fs::read_to_string(dir.join("report.md")).unwrap();
    assert!(report.contains("**Verdict: the defaults are"), "{report}");
    // The reference accumulates in f64; the same accumulated in f32 is noted beside it,
    // as close to it as f32 rounding of a few hundred blend steps.
    assert!(
        report.contains("accumulated in f64 (`render.f64_accumulation`)"),
        "{report}"
    );
    let f32_rmse: f64 = report
        .split("accumulated in f32 instead: RMSE ")
        .nth(1)
        .and_then(|r| r.split(',').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no f32 note: {report}"));
    assert!(f32_rmse < 1e-5, "f32 against f64 reference: {f32_rmse}");
    assert!(report.contains("![step](step.png)"));
    for stem in ["step", "tau", "early-termination", "step-and-tau"] {
        let png = std::fs::read(dir.join(format!("{stem}.png"))).unwrap();
        assert_eq!(&png[1..4], b"PNG", "{stem}.png");
        let svg = std::fs::read_to_string(dir.join(format!("{stem}.svg"))).unwrap();
        assert!(
            svg.contains("<svg") && svg.contains("time per frame"),
            "{stem}.svg"
        );
    }
    // The rebuilt stores lived in a scratch folder that is gone.
    let left: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(left.is_empty(), "{left:?}");
}

#[test]
fn a_missing_scene_is_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let out = Command::new(BIN)
        .args(["-q", "study", "accuracy", "/nonexistent/scene.toml", "-o"])
        .arg(tmp.path().join("o"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("/nonexistent/scene.toml"), "{err}");
}

/// A scene with a `[wall]` is refused before anything renders: the study renders one image
/// (its distributed points had failed on the wall's tile files, each noted as skipped).
#[test]
fn a_wall_scene_is_refused_naming_the_wall() {
    let tmp = tempfile::tempdir().unwrap();
    let survey = common::survey_in("study-survey");
    let text = std::fs::read_to_string(survey.join("scene.toml")).unwrap();
    // Beside the survey's scene, so its relative store paths hold.
    let scene_in = survey.join("wall-study.toml");
    std::fs::write(
        &scene_in,
        format!("{text}\n[wall]\ntiles = [2, 1]\ntile_size = [24, 16]\nmullion = [0, 0]\n"),
    )
    .unwrap();
    let out = Command::new(BIN)
        .args(["-q", "study", "accuracy"])
        .arg(&scene_in)
        .arg("-o")
        .arg(tmp.path().join("o"))
        .args(["--size", "48x32", "--no-gpu"])
        .output()
        .unwrap();
    let _ = std::fs::remove_file(&scene_in);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("[wall]") && err.contains("wall-study.toml"),
        "{err}"
    );
    assert!(!tmp.path().join("o").join("points.csv").exists());
}
