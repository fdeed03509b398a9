//! The `coordinator` binary end to end: help, errors and exit codes, no half-written output.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn coordinator(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .arg("-q")
        .args(args)
        .output()
        .unwrap()
}

fn real(rel: &str) -> String {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/real")
        .join(rel)
        .display()
        .to_string()
}

fn only_files(dir: &Path) -> Vec<String> {
    let mut v: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn help_everywhere() {
    for args in [
        &["--help"][..],
        &["ingest", "--help"],
        &["ingest", "segy", "--help"],
        &["ingest", "raw", "--help"],
        &["ingest", "horizon", "--help"],
        &["synth", "--help"],
        &["inspect", "--help"],
        &["render", "--help"],
        &["study", "--help"],
        &["study", "accuracy", "--help"],
        &["worker", "--help"],
    ] {
        let o = coordinator(args);
        assert!(o.status.success(), "{args:?}");
        assert!(
            String::from_utf8_lossy(&o.stdout).contains("Usage"),
            "{args:?}"
        );
    }
}

#[test]
fn bad_inputs_fail_cleanly_and_leave_nothing_behind() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Truncated SEG-Y.
    let bytes = std::fs::read(real("seismic/f3_segyio/f3.sgy")).unwrap();
    std::fs::write(d.join("cut.sgy"), &bytes[..bytes.len() - 100]).unwrap();
    // Unknown sample format code (bytes 3225-3226, big-endian) = 4.
    let mut bad = bytes.clone();
    bad[3224] = 0;
    bad[3225] = 99;
    std::fs::write(d.join("fmt.sgy"), &bad).unwrap();
    std::fs::write(d.join("garbage.sgy"), vec![0xA5u8; 5000]).unwrap();
    std::fs::write(d.join("v.raw"), vec![1u8; 999]).unwrap();
    std::fs::write(d.join("h.txt"), "# horizon\n100 200 1.5\n101 200 abc\n").unwrap();
    let out = d.join("out.strata").display().to_string();
    let p = |n: &str| d.join(n).display().to_string();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec![
                "ingest".into(),
                "segy".into(),
                p("cut.sgy"),
                "-o".into(),
                out.clone(),
            ],
            "cut.sgy",
        ),
        (
            vec![
                "ingest".into(),
                "segy".into(),
                p("fmt.sgy"),
                "-o".into(),
                out.clone(),
            ],
            "fmt.sgy",
        ),
        (
            vec![
                "ingest".into(),
                "segy".into(),
                p("garbage.sgy"),
                "-o".into(),
                out.clone(),
            ],
            "garbage.sgy",
        ),
        (
            vec![
                "ingest".into(),
                "raw".into(),
                p("v.raw"),
                "--dims".into(),
                "10".into(),
                "10".into(),
                "10".into(),
                "--dtype".into(),
                "u8".into(),
                "-o".into(),
                out.clone(),
            ],
            "v.raw",
        ),
        (
            vec![
                "ingest".into(),
                "horizon".into(),
                p("h.txt"),
                "-o".into(),
                out.clone(),
            ],
            "h.txt:3",
        ),
        (vec!["inspect".into(), p("v.raw")], "v.raw"),
        (
            vec![
                "ingest".into(),
                "segy".into(),
                p("missing.sgy"),
                "-o".into(),
                out.clone(),
            ],
            "missing.sgy",
        ),
    ];
    let before = only_files(d);
    for (args, names) in cases {
        let a: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
        let o = coordinator(&a);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{a:?}: {err}");
        assert!(
            err.contains("error:") && err.contains(names),
            "{a:?}: {err}"
        );
        assert!(!err.contains("panicked"), "{a:?}: {err}");
        assert_eq!(
            err.trim()
                .lines()
                .filter(|l| l.starts_with("error:"))
                .count(),
            1,
            "{err}"
        );
        assert_eq!(only_files(d), before, "{a:?} left files behind");
    }
    // Usage errors are clap's (exit 2).
    assert_eq!(coordinator(&["ingest", "raw", "x"]).status.code(), Some(2));
}

#[test]
fn synth_is_deterministic_and_round_trips_through_segy_and_text() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let s1 = d.join("a").display().to_string();
    let s2 = d.join("b").display().to_string();
    for s in [&s1, &s2] {
        let o = coordinator(&[
            "synth", "-o", s, "--size", "70", "50", "60", "--seed", "5", "--segy",
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    let digest = |store: &str| -> String {
        let o = coordinator(&["inspect", store, "--verify"]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stdout)
            .lines()
            .find(|l| l.starts_with("digest: "))
            .unwrap()
            .to_string()
    };
    let a = digest(&format!("{s1}/seismic.strata"));
    assert_eq!(a, digest(&format!("{s2}/seismic.strata")));
    // The SEG-Y copy ingests to the same samples (IEEE float is exact).
    let o = coordinator(&[
        "ingest",
        "segy",
        &format!("{s1}/seismic.sgy"),
        "-o",
        &format!("{s1}/again.strata"),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(a, digest(&format!("{s1}/again.strata")));
    // Horizon text with holes left out, placed on the survey of the cube: same heights as the synth's store.
    for h in 1..=3 {
        let o = coordinator(&[
            "ingest",
            "horizon",
            &format!("{s1}/horizon{h}.txt"),
            "--survey",
            &format!("{s1}/again.strata"),
            "-o",
            &format!("{s1}/h{h}.strata"),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        // Text keeps 3 decimals, so compare the stores' value ranges loosely and the hole count exactly.
        let info =
            |p: &str| String::from_utf8_lossy(&coordinator(&["inspect", p]).stdout).to_string();
        let valid = |t: &str| {
            t.lines()
                .find(|l| l.starts_with("valid samples"))
                .unwrap()
                .to_string()
        };
        assert_eq!(
            valid(&info(&format!("{s1}/h{h}.strata"))),
            valid(&info(&format!("{s1}/horizon{h}.strata")))
        );
    }
    let scene = std::fs::read_to_string(format!("{s1}/scene.toml")).unwrap();
    let parsed =
        strata_common::scene::Scene::parse(Path::new(&format!("{s1}/scene.toml")), &scene).unwrap();
    assert_eq!(parsed.volumes.len(), 1);
    assert_eq!(parsed.horizons.len(), 3);
    assert!(parsed.volumes[0].store.exists());
}

#[test]
fn depth_cubes_keep_their_domain_and_unit_through_ingest() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = |n: &str| d.join(n).display().to_string();
    let f3 = real("seismic/f3_segyio/f3.sgy");
    let inspect = |store: &str| {
        let o = coordinator(&["inspect", store]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stdout).to_string()
    };
    // Said nothing: time in ms.
    let o = coordinator(&["ingest", "segy", &f3, "-o", &out("t.strata")]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(inspect(&out("t.strata")).contains("vertical ms (time)"));
    // Told depth in feet, 2.5 ft per sample: never labelled ms, and z steps 2.5.
    let o = coordinator(&[
        "ingest",
        "segy",
        &f3,
        "--vertical",
        "depth",
        "--vertical-unit",
        "ft",
        "--z-step",
        "2.5",
        "-o",
        &out("z.strata"),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = inspect(&out("z.strata"));
    assert!(text.contains("vertical ft (depth)"), "{text}");
    assert!(
        text.contains("[0.0, 0.0, 2.5, "),
        "z row of the transform steps 2.5: {text}"
    );
    // A horizon placed on that survey takes its vertical axis.
    std::fs::write(
        d.join("h.txt"),
        "111 875 100\n111 876 101\n112 875 102\n112 876 103\n",
    )
    .unwrap();
    let o = coordinator(&[
        "ingest",
        "horizon",
        &out("h.txt"),
        "--survey",
        &out("z.strata"),
        "-o",
        &out("h.strata"),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(inspect(&out("h.strata")).contains("vertical ft (depth)"));
    // Contradictions are one-line errors that leave nothing behind.
    for (args, want) in [
        (
            vec!["--vertical", "time", "--vertical-unit", "m"],
            "is a depth unit",
        ),
        (vec!["--offset", "100", "--stack"], "cannot be used with"),
        (vec!["--offset", "7"], "no trace has offset 7"),
    ] {
        let mut a = vec!["ingest", "segy", f3.as_str()];
        a.extend(args);
        let bad = out("bad.strata");
        a.extend(["-o", bad.as_str()]);
        let o = coordinator(&a);
        assert!(!o.status.success());
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains(want), "{e}");
        assert!(!d.join("bad.strata").exists());
    }
}

#[test]
fn example_scene_parses() {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs/example.toml");
    let s = strata_common::scene::Scene::parse(&p, &std::fs::read_to_string(&p).unwrap()).unwrap();
    assert_eq!((s.volumes.len(), s.horizons.len()), (1, 3));
    assert_eq!(s.render.cache_mb, 1024);
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs/wall.toml");
    let s = strata_common::scene::Scene::parse(&p, &std::fs::read_to_string(&p).unwrap()).unwrap();
    let w = s.wall.unwrap();
    assert_eq!(
        (w.tiles, w.tile_size, w.mullion),
        ([3, 2], [1920, 1080], [40, 40])
    );
}

/// A wall sequence: every frame writes its numbered tiles and preview; a second run finds
/// them complete and skips every frame; a missing tile makes its frame render again.
#[test]
fn wall_sequences_number_their_tiles_and_resume() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene = small_survey(d).join("scene.toml");
    let out = d.join("frames/frame_%05d.png");
    std::fs::create_dir_all(d.join("frames")).unwrap();
    let args = [
        "render",
        scene.to_str().unwrap(),
        "--in-process",
        "--orbit",
        "3",
        "-o",
        out.to_str().unwrap(),
        "--set",
        "wall.tiles=[2,1]",
        "--set",
        "wall.tile_size=[16,12]",
        "--set",
        "wall.mullion=[3,0]",
    ];
    let o = coordinator(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in 0..3 {
        for name in [
            format!("frame_{f:05}.png"),
            format!("frame_{f:05}_c0r0.png"),
            format!("frame_{f:05}_c1r0.png"),
        ] {
            assert!(d.join("frames").join(&name).is_file(), "{name}");
        }
    }
    let o = coordinator(&args);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        text.contains("all 3 frame(s) of the range exist complete"),
        "{text}"
    );
    std::fs::remove_file(d.join("frames/frame_00001_c1r0.png")).unwrap();
    let o = coordinator(&args);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("2 frame(s) skipped"), "{text}");
    assert!(d.join("frames/frame_00001_c1r0.png").is_file());

    // Without the preview mosaic only tiles are written: the summary names tiles that
    // exist, and a video of the (unwritten) -o frames is refused before anything renders.
    let tiles_only = d.join("tiles/t_%02d.png");
    let mut a = args.to_vec();
    a[6] = tiles_only.to_str().unwrap();
    a.extend(["--set", "wall.preview=false"]);
    let o = coordinator(&a);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    let line = text
        .lines()
        .find(|l| l.starts_with("wrote"))
        .unwrap_or_default();
    for name in ["t_00_c0r0.png", "t_02_c1r0.png"] {
        assert!(line.contains(name), "{text}");
        assert!(d.join("tiles").join(name).is_file(), "{name}");
    }
    assert!(!d.join("tiles/t_00.png").exists());
    let video = d.join("tiles/v.mp4");
    a.extend(["--mp4", video.to_str().unwrap(), "--frames", "0..1"]);
    std::fs::remove_dir_all(d.join("tiles")).unwrap();
    let o = coordinator(&a);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("wall.preview"), "{err}");
    // Refused before the frames' folder is made.
    assert!(!d.join("tiles").exists());
}

/// A 40×32×24 synthetic survey (volume and three horizons) in `dir/survey`.
fn small_survey(dir: &Path) -> PathBuf {
    let survey = dir.join("survey");
    let o = coordinator(&[
        "synth",
        "-o",
        survey.to_str().unwrap(),
        "--size",
        "40",
        "32",
        "24",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    survey
}

#[test]
fn camera_path_sequences_split_into_ranges_and_resume() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let survey = small_survey(d);
    let scene = survey.join("scene.toml");
    // The survey spans about 1000 × 800 m from (605000, 6075000); z grows downward.
    let toml = r#"
interpolation = "smooth"
fps = 3
[[keyframes]]
time = 0.0
eye = [604200.0, 6074000.0, -1500.0]
target = [605500.0, 6075400.0, 300.0]
up = [0.0, 0.0, -1.0]
[[keyframes]]
time = 1.0
eye = [606800.0, 6074200.0, -1500.0]
target = [605500.0, 6075400.0, 300.0]
up = [0.0, 0.0, -1.0]
"#;
    let path = d.join("path.toml");
    std::fs::write(&path, toml).unwrap();
    let out = d.join("out");
    std::fs::create_dir(&out).unwrap();
    let pattern = out.join("f_%02d.png");
    let render = |extra: &[&str]| {
        let mut args = vec![
            "render",
            scene.to_str().unwrap(),
            "--in-process",
            "--size",
            "48x32",
            "-o",
            pattern.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        coordinator(&args)
    };
    let path_arg = path.to_str().unwrap();
    // Frames 1 and 2 of the 4 (0, ⅓, ⅔, 1 s): one job of an array.
    let o = render(&["--path", path_arg, "--frames", "1..3"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(only_files(&out), ["f_01.png", "f_02.png"]);
    let f1 = std::fs::read(out.join("f_01.png")).unwrap();
    // The rest, resumed: 1 and 2 are complete and skipped; a damaged frame 3 is redone.
    std::fs::write(out.join("f_03.png"), b"\x89PNG truncated").unwrap();
    let o = render(&["--path", path_arg, "--frames", "0..=3"]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(stdout.contains("2 frame(s) skipped"), "{stdout}");
    assert_eq!(
        only_files(&out),
        ["f_00.png", "f_01.png", "f_02.png", "f_03.png"]
    );
    assert_eq!(std::fs::read(out.join("f_01.png")).unwrap(), f1);
    let frames: Vec<Vec<u8>> = (0..4)
        .map(|i| std::fs::read(out.join(format!("f_{i:02}.png"))).unwrap())
        .collect();
    assert!(frames.windows(2).all(|w| w[0] != w[1]), "the camera moves");
    // All complete: nothing rendered, and the stats say so.
    let skipped_stats = d.join("skipped.jsonl");
    let o = render(&[
        "--path",
        path_arg,
        "--stats",
        skipped_stats.to_str().unwrap(),
    ]);
    assert!(o.status.success());
    assert!(String::from_utf8_lossy(&o.stdout).contains("nothing to render"));
    let text = std::fs::read_to_string(&skipped_stats).unwrap();
    assert!(text.contains("\"skipped\":4"), "{text}");

    // The same path in JSON renders the same frames.
    let json = d.join("path.json");
    std::fs::write(
        &json,
        r#"{"interpolation": "smooth", "fps": 3, "keyframes": [
            {"time": 0.0, "eye": [604200.0, 6074000.0, -1500.0], "target": [605500.0, 6075400.0, 300.0], "up": [0.0, 0.0, -1.0]},
            {"time": 1.0, "eye": [606800.0, 6074200.0, -1500.0], "target": [605500.0, 6075400.0, 300.0], "up": [0.0, 0.0, -1.0]}]}"#,
    )
    .unwrap();
    let jpattern = out.join("j_%02d.png");
    let o = coordinator(&[
        "render",
        scene.to_str().unwrap(),
        "--in-process",
        "--size",
        "48x32",
        "-o",
        jpattern.to_str().unwrap(),
        "--path",
        json.to_str().unwrap(),
        "--frames",
        "2..3",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(std::fs::read(out.join("j_02.png")).unwrap(), frames[2]);

    // Bad paths and ranges: clear errors naming the file, non-zero exit, nothing written.
    let bad = d.join("bad.toml");
    std::fs::write(&bad, toml.replace("time = 1.0", "time = 0.0")).unwrap();
    let empty = d.join("empty");
    std::fs::create_dir(&empty).unwrap();
    // The frames' folder does not exist yet: a refused command must not make it.
    let epattern = empty.join("sub").join("e_%02d.png");
    let unnumbered_exr = empty.join("sub").join("x.exr");
    for (args, want) in [
        (vec!["--orbit", "0"], "1..="),
        (
            vec!["--orbit", "3", "--exr", unnumbered_exr.to_str().unwrap()],
            "frame-number pattern",
        ),
        (vec!["--path", bad.to_str().unwrap()], "keyframe 1"),
        (
            vec!["--path", "/nonexistent/path.toml"],
            "/nonexistent/path.toml",
        ),
        (vec!["--path", path_arg, "--frames", "3..1"], "no frame"),
        (vec!["--path", path_arg, "--frames", "7..9"], "0..4"),
        (vec!["--frames", "0..2"], "--orbit N or --path"),
    ] {
        let mut a = vec![
            "render",
            scene.to_str().unwrap(),
            "--in-process",
            "--size",
            "48x32",
            "-o",
            epattern.to_str().unwrap(),
        ];
        a.extend_from_slice(&args);
        let o = coordinator(&a);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{args:?}");
        assert!(err.contains(want), "{args:?}: {err}");
        assert!(
            std::fs::read_dir(&empty).unwrap().next().is_none(),
            "{args:?}: the refused command left something in {}",
            empty.display()
        );
    }
}

#[test]
fn mp4_uses_ffmpeg_when_there_is_one_and_says_so_when_not() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let survey = small_survey(d);
    let out = d.join("out");
    std::fs::create_dir(&out).unwrap();
    let bin = d.join("bin");
    std::fs::create_dir(&bin).unwrap();
    let mp4 = d.join("seq.mp4");
    let run = |path_env: &Path, frames: &str| {
        Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .env("PATH", path_env)
            .args(["-q", "render"])
            .arg(survey.join("scene.toml"))
            .args([
                "--in-process",
                "--size",
                "32x24",
                "--orbit",
                "4",
                "--frames",
                frames,
            ])
            .arg("-o")
            .arg(out.join("f_%03d.png"))
            .arg("--mp4")
            .arg(&mp4)
            .output()
            .unwrap()
    };
    // The video and the stats may go into the folder the frames' pattern makes.
    let fresh = d.join("fresh");
    let o = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .env("PATH", &bin)
        .args(["-q", "render"])
        .arg(survey.join("scene.toml"))
        .args(["--in-process", "--size", "32x24", "--orbit", "2"])
        .arg("-o")
        .arg(fresh.join("f_%03d.png"))
        .arg("--mp4")
        .arg(fresh.join("v.mp4"))
        .arg("--stats")
        .arg(fresh.join("s.jsonl"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(fresh.join("s.jsonl").is_file());
    // No ffmpeg: the frames are written, the run succeeds, and a note says why no MP4.
    let o = run(&bin, "1..3");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("ffmpeg is not on the PATH"), "{err}");
    assert!(!mp4.exists());
    assert_eq!(only_files(&out), ["f_001.png", "f_002.png"]);
    // A stand-in ffmpeg that records its arguments and writes the output it is given.
    let fake = bin.join("ffmpeg");
    std::fs::write(
        &fake,
        format!(
            "#!/bin/sh\necho \"$@\" > {}\nfor a; do last=$a; done\necho mp4 > \"$last\"\n",
            d.join("args").display()
        ),
    )
    .unwrap();
    std::fs::set_permissions(&fake, std::fs::Permissions::from_mode(0o755)).unwrap();
    let o = run(&bin, "1..3");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("nothing to render"));
    assert_eq!(std::fs::read_to_string(&mp4).unwrap(), "mp4\n");
    let args = std::fs::read_to_string(d.join("args")).unwrap();
    assert!(
        args.contains("-framerate 24 -start_number 1 -i") && args.contains("f_%03d.png"),
        "{args}"
    );
    // Frames 1 and 2 only (frame 3 of another part may lie beside them), odd sides padded.
    assert!(args.contains("-frames:v 2 "), "{args}");
    assert!(args.contains("pad=ceil(iw/2)*2:ceil(ih/2)*2"), "{args}");
    assert!(!only_files(d).iter().any(|f| f.contains("partial")));
    // A failing ffmpeg fails the run with its message, and leaves no MP4 behind.
    std::fs::write(&fake, "#!/bin/sh\necho 'codec not found' >&2\nexit 1\n").unwrap();
    std::fs::remove_file(&mp4).unwrap();
    let o = run(&bin, "1..3");
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("codec not found"));
    assert!(!mp4.exists());
}

#[test]
fn rounds_per_frame_bounds_the_refinement_of_later_frames() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let survey = d.join("survey");
    let o = coordinator(&[
        "synth",
        "-o",
        survey.to_str().unwrap(),
        "--size",
        "128",
        "128",
        "64",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // Frame 0 from far away (the root pages suffice), frame 1 close (level-0 pages needed).
    let path = d.join("p.toml");
    std::fs::write(
        &path,
        r#"
interpolation = "linear"
fps = 1
[[keyframes]]
time = 0.0
eye = [500000.0, 6000000.0, -60000.0]
target = [606062.0, 6076997.0, 128.0]
up = [0.0, 0.0, -1.0]
[[keyframes]]
time = 1.0
eye = [601989.0, 6074282.0, -777.0]
target = [606062.0, 6076997.0, 128.0]
up = [0.0, 0.0, -1.0]
"#,
    )
    .unwrap();
    let frames = |rpf: &str| -> Vec<serde_json::Value> {
        let out = d.join(format!("out{rpf}"));
        std::fs::create_dir(&out).unwrap();
        let stats = d.join(format!("s{rpf}.jsonl"));
        let set = format!("render.rounds_per_frame={rpf}");
        let o = coordinator(&[
            "render",
            survey.join("scene.toml").to_str().unwrap(),
            "--in-process",
            "--path",
            path.to_str().unwrap(),
            "-o",
            out.join("f_%d.png").to_str().unwrap(),
            "--size",
            "160x120",
            "--set",
            &set,
            "--stats",
            stats.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        std::fs::read_to_string(&stats)
            .unwrap()
            .lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
            .filter(|v| v["kind"] == "frame")
            .collect()
    };
    // Unbounded: the close frame loads its pages and converges in a second round.
    let free = frames("0");
    assert_eq!(
        (free[1]["rounds"].as_u64(), free[1]["outcome"].as_str()),
        (Some(2), Some("converged"))
    );
    // Bounded to one round: it renders with what the previous frame left resident; its
    // requests are loaded for the frame after.
    let bounded = frames("1");
    assert_eq!(bounded[0]["outcome"], "converged");
    assert_eq!(
        (
            bounded[1]["rounds"].as_u64(),
            bounded[1]["outcome"].as_str()
        ),
        (Some(1), Some("round-limit"))
    );
}

/// Outputs and values are checked before any work: a missing folder, an output that is an
/// input, a value no render can use, a scene value (named with its line), a timeout no
/// clock can hold. Each fails with one error, exit 1, no panic and nothing written.
#[test]
fn outputs_and_values_are_checked_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let survey = small_survey(d);
    let scene = survey.join("scene.toml");
    let scene_s = scene.to_str().unwrap();
    let scene_text = std::fs::read_to_string(&scene).unwrap();
    std::fs::write(d.join("v.raw"), vec![1u8; 1000]).unwrap();
    let bad_fov = d.join("fov.toml");
    assert!(scene_text.contains("\nfov_deg = 35.0\n"), "{scene_text}");
    std::fs::write(
        &bad_fov,
        scene_text.replace("fov_deg = 35.0", "fov_deg = 0.0"),
    )
    .unwrap();
    let fov_line = 1 + scene_text[..scene_text.find("fov_deg").unwrap()]
        .matches('\n')
        .count();
    // A path whose keyframes are fine but whose linear interpolation puts the eye on the
    // target at t = 0.5 (frame 1 at 2 fps).
    let through = d.join("through.toml");
    std::fs::write(
        &through,
        "interpolation = \"linear\"\nfps = 2\n\
         [[keyframes]]\ntime = 0.0\neye = [604300.0, 6075300.0, 100.0]\ntarget = [605300.0, 6075300.0, 100.0]\n\
         [[keyframes]]\ntime = 1.0\neye = [606300.0, 6075300.0, 100.0]\ntarget = [605300.0, 6075300.0, 100.0]\n",
    )
    .unwrap();
    let p = |n: &str| d.join(n).display().to_string();
    let render = |extra: &[&str]| -> Vec<String> {
        let mut v: Vec<String> = ["render", scene_s, "--in-process", "--size", "32x24"]
            .map(String::from)
            .to_vec();
        v.extend(extra.iter().map(|s| s.to_string()));
        v
    };
    let cases: Vec<(Vec<String>, String)> = vec![
        (render(&["-o", &p("nodir/o.png")]), "nodir".into()),
        (
            render(&["-o", &p("o.png"), "--exr", &p("nodir/o.exr")]),
            "nodir".into(),
        ),
        (
            render(&["-o", &p("o.png"), "--stats", &p("nodir/s.jsonl")]),
            "nodir".into(),
        ),
        (render(&["-o", scene_s]), "this is the input".into()),
        (
            render(&["-o", &p("f_%03d.png"), "--path", through.to_str().unwrap()]),
            "frame 1".into(),
        ),
        (
            render(&["-o", &p("o.png"), "--set", "render.atlas_mb=100000000"]),
            "render.atlas_mb".into(),
        ),
        (
            render(&["-o", &p("o.png"), "--set", "render.z_scale=1e300"]),
            "render.z_scale".into(),
        ),
        (
            vec![
                "render".into(),
                bad_fov.display().to_string(),
                "--in-process".into(),
                "-o".into(),
                p("o.png"),
            ],
            format!("fov.toml:{fov_line}:1: camera.fov_deg"),
        ),
        (
            [
                "ingest",
                "raw",
                &p("v.raw"),
                "--dims",
                "10",
                "10",
                "10",
                "--dtype",
                "u8",
                "-o",
                &p("v.raw"),
            ]
            .map(String::from)
            .to_vec(),
            "this is the input".into(),
        ),
        (
            ["synth", "-o", &p("tiny"), "--size", "2", "2", "2"]
                .map(String::from)
                .to_vec(),
            "at least 8 samples".into(),
        ),
        (
            render(&["-o", &p("o.png"), "--exr", &p("o.png")]),
            "same file".into(),
        ),
        (
            render(&[
                "-o",
                &p("o.png"),
                "--stats",
                &format!("{}/./o.png", d.display()),
            ]),
            "same file".into(),
        ),
        // A video written over one of the frames it encodes.
        (
            render(&[
                "-o",
                &p("f_%03d.png"),
                "--orbit",
                "3",
                "--mp4",
                &format!("{}/./f_002.png", d.display()),
            ]),
            "is one of the frames of the image (-o)".into(),
        ),
        // The frame number names files, not folders.
        (
            render(&["-o", &p("shot_%02d/img.png"), "--orbit", "2"]),
            "must be in the file name".into(),
        ),
        // A sequence's folder is made only once every output passed its checks.
        (
            render(&[
                "-o",
                &p("seq/f_%03d.png"),
                "--orbit",
                "2",
                "--stats",
                d.to_str().unwrap(),
            ]),
            "is a folder".into(),
        ),
        (
            [
                "render",
                scene_s,
                "--workers",
                "2",
                "--set",
                "cluster.worker_threads=100000",
                "-o",
                &p("o.png"),
            ]
            .map(String::from)
            .to_vec(),
            "cluster.worker_threads".into(),
        ),
        (
            [
                "render",
                scene_s,
                "--workers",
                "2",
                "--set",
                "composite.k=[0]",
                "-o",
                &p("o.png"),
            ]
            .map(String::from)
            .to_vec(),
            "composite.k = [0]: exact factors are a list of at least two".into(),
        ),
        (
            render(&["-o", &p("o.png"), "--stats", d.to_str().unwrap()]),
            "is a folder".into(),
        ),
    ];
    let before = only_files(d);
    for (args, needle) in cases {
        let a: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
        let o = coordinator(&a);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{a:?}: {err}");
        assert!(err.contains(&needle), "{a:?}: expected {needle:?} in {err}");
        assert!(!err.contains("panicked"), "{a:?}: {err}");
        assert_eq!(only_files(d), before, "{a:?} left files behind");
    }
    assert_eq!(std::fs::read_to_string(&scene).unwrap(), scene_text);
    assert_eq!(std::fs::read(d.join("v.raw")).unwrap(), vec![1u8; 1000]);
    // A `%%` in the folder of a pattern is a `%`: the folder made is the one the frames go
    // to (it was made as `100%%`, and the frames failed after the render).
    let a = render(&["-o", &p("100%%/f_%03d.png"), "--orbit", "2"]);
    let a: Vec<&str> = a.iter().map(|s| s.as_str()).collect();
    let o = coordinator(&a);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(d.join("100%/f_001.png").is_file());
    assert!(!d.join("100%%").exists());
    std::fs::remove_dir_all(d.join("100%")).unwrap();
    // A worker's timeouts are bounded as the coordinator's are.
    for flag in ["--connect-timeout-s", "--idle-timeout-s"] {
        let o = Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(["-q", "worker", "--connect", "127.0.0.1:9", "--fingerprint"])
            .arg("ab".repeat(32))
            .args([flag, "inf"])
            .env("STRATA_SECRET", "0123456789abcdef0123")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{flag}: {err}");
        assert!(err.contains(flag) && !err.contains("panicked"), "{err}");
    }
    // A fingerprint file every user may write is refused; the same file without that
    // permission is read (and the worker then finds no coordinator in its short timeout).
    let fp = d.join("fingerprint");
    std::fs::write(&fp, format!("{}\n", "ab".repeat(32))).unwrap();
    for (mode, refused) in [(0o666, true), (0o644, false)] {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&fp, std::fs::Permissions::from_mode(mode)).unwrap();
        let o = Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args([
                "-q",
                "worker",
                "--connect",
                "127.0.0.1:9",
                "--fingerprint-file",
            ])
            .arg(&fp)
            .args(["--connect-timeout-s", "0.3"])
            .env("STRATA_SECRET", "0123456789abcdef0123")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{mode:o}: {err}");
        assert_eq!(
            err.contains("writable by every user"),
            refused,
            "{mode:o}: {err}"
        );
        assert!(!err.contains("panicked"), "{err}");
    }
    // So is one in a folder every user may write (not sticky), where another user could
    // replace it, and (where this test may give it away) one another user owns.
    let worker_with = |fp: &std::path::Path| {
        let o = Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(["-q", "worker", "--connect", "127.0.0.1:9"])
            .arg("--fingerprint-file")
            .arg(fp)
            .args(["--connect-timeout-s", "0.3"])
            .env("STRATA_SECRET", "0123456789abcdef0123")
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(1));
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    {
        use std::os::unix::fs::PermissionsExt;
        let open = d.join("open");
        std::fs::create_dir(&open).unwrap();
        let fp2 = open.join("fingerprint");
        std::fs::copy(&fp, &fp2).unwrap();
        std::fs::set_permissions(&open, std::fs::Permissions::from_mode(0o777)).unwrap();
        let err = worker_with(&fp2);
        assert!(err.contains("not sticky (mode 777)"), "{err}");
        // A link from a private folder to it is no better: the real path's folders count.
        let link = d.join("link");
        std::os::unix::fs::symlink(&fp2, &link).unwrap();
        let err = worker_with(&link);
        assert!(err.contains("not sticky (mode 777)"), "{err}");
        std::fs::set_permissions(&open, std::fs::Permissions::from_mode(0o1777)).unwrap();
        let err = worker_with(&fp2);
        assert!(
            !err.contains("sticky") && !err.contains("panicked"),
            "{err}"
        );
        std::fs::set_permissions(&open, std::fs::Permissions::from_mode(0o700)).unwrap();
        if std::os::unix::fs::chown(&fp2, Some(4242), None).is_ok() {
            let err = worker_with(&fp2);
            assert!(err.contains("owned by user 4242"), "{err}");
        }
    }
}

/// A build ended by a signal leaves no temporary behind, and still dies of that signal.
#[test]
fn an_interrupted_build_leaves_no_temporary() {
    use std::os::unix::process::ExitStatusExt;
    for signal in [libc::SIGTERM, libc::SIGINT] {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("big");
        let mut child = Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args([
                "-q",
                "synth",
                "-o",
                out.to_str().unwrap(),
                "--size",
                "700",
                "600",
                "500",
            ])
            .spawn()
            .unwrap();
        // Wait for the store's temporary to appear, then interrupt the build.
        let t0 = std::time::Instant::now();
        let temporaries = || -> Vec<String> {
            std::fs::read_dir(&out)
                .map(|d| {
                    d.filter_map(|e| e.ok())
                        .map(|e| e.file_name().to_string_lossy().into_owned())
                        .filter(|n| n.contains(".tmp"))
                        .collect()
                })
                .unwrap_or_default()
        };
        while temporaries().is_empty() {
            assert!(
                t0.elapsed().as_secs() < 60,
                "no temporary appeared in {out:?}"
            );
            if let Some(s) = child.try_wait().unwrap() {
                panic!("the build ended ({s}) before it could be interrupted");
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
        // SAFETY: signals our own child.
        unsafe { libc::kill(child.id() as i32, signal) };
        let status = child.wait().unwrap();
        assert_eq!(status.signal(), Some(signal), "{status}");
        assert_eq!(temporaries(), Vec::<String>::new(), "left behind");
    }
    // A build started with SIGHUP ignored (`nohup`) is not ended by one.
    use std::os::unix::process::CommandExt;
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("hup");
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_coordinator"));
    cmd.args([
        "-q",
        "synth",
        "-o",
        out.to_str().unwrap(),
        "--size",
        "400",
        "300",
        "300",
    ]);
    // SAFETY: `signal` is async-signal-safe; it runs in the child before exec.
    unsafe {
        cmd.pre_exec(|| {
            libc::signal(libc::SIGHUP, libc::SIG_IGN);
            Ok(())
        });
    }
    let mut child = cmd.spawn().unwrap();
    let t0 = std::time::Instant::now();
    while !std::fs::read_dir(&out).is_ok_and(|d| {
        d.filter_map(|e| e.ok())
            .any(|e| e.file_name().to_string_lossy().contains(".tmp"))
    }) {
        assert!(t0.elapsed().as_secs() < 60, "no temporary appeared");
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    // SAFETY: signals our own child.
    unsafe { libc::kill(child.id() as i32, libc::SIGHUP) };
    let status = child.wait().unwrap();
    assert!(
        status.success(),
        "an ignored SIGHUP ended the build: {status}"
    );
    assert!(out.join("scene.toml").exists());
}

/// The README's first command, as a fresh checkout runs it: the demo scene generates its
/// survey on first use (here into a fresh folder beside a copy of configs/demo.toml), local
/// workers are spawned and the image is composited from them. Only the size is smaller
/// (`--size`, to keep the test short); the command is checked against the README's.
#[test]
fn the_readme_demo_command_renders_on_a_fresh_checkout() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let command = "cargo run --release --bin coordinator -- render configs/demo.toml -o demo.png";
    assert!(
        readme.contains(&format!("```sh\n{command}\n```")),
        "README.md no longer shows {command:?}: update this test with it"
    );
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("demo.toml");
    std::fs::copy(root.join("configs/demo.toml"), &scene).unwrap();
    let out = dir.path().join("demo.png");
    let o = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .arg("render")
        .arg(&scene)
        .arg("-o")
        .arg(&out)
        .args(["--size", "160x90"])
        .output()
        .unwrap();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert!(o.status.success(), "{stdout}\n{stderr}");
    // Generated on first use, beside the scene.
    assert!(dir.path().join("synthetic/demo/seismic.strata").is_file());
    for h in 1..=3 {
        assert!(dir
            .path()
            .join(format!("synthetic/demo/horizon{h}.strata"))
            .is_file());
    }
    // Rendered by spawned workers, not in process.
    assert!(stdout.contains("workers, "), "{stdout}");
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&out).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!((info.width, info.height), (160, 90));
    // The slices and horizons cover much of the frame over the black background.
    let lit = buf
        .chunks_exact(3)
        .filter(|p| p.iter().any(|&c| c > 8))
        .count();
    assert!(
        lit > 160 * 90 / 4,
        "{lit} of {} pixels show something",
        160 * 90
    );
}

/// A resumed sequence re-renders a frame whose EXR is damaged, or of an earlier run at
/// another size, and skips the frames whose PNG and EXR are both whole at this size (an
/// EXR counted as complete when it merely existed).
#[test]
fn resume_checks_the_exr_too() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let survey = small_survey(d);
    let out = d.join("out");
    std::fs::create_dir(&out).unwrap();
    let run = |size: &str, exr: bool| {
        let mut a: Vec<String> = ["render", survey.join("scene.toml").to_str().unwrap()]
            .map(String::from)
            .to_vec();
        for s in ["--in-process", "--orbit", "3", "--size", size, "-o"] {
            a.push(s.into());
        }
        a.push(out.join("f_%02d.png").display().to_string());
        if exr {
            a.push("--exr".into());
            a.push(out.join("f_%02d.exr").display().to_string());
        }
        let refs: Vec<&str> = a.iter().map(String::as_str).collect();
        let o = coordinator(&refs);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    let size_of = |n: &str| {
        let m = exr::meta::MetaData::read_from_file(out.join(n), false).unwrap();
        let s = m.headers[0].layer_size;
        (s.0, s.1)
    };
    run("24x16", true);
    // The PNGs at another size, without EXRs: those stay 24 × 16.
    run("32x20", false);
    assert_eq!(size_of("f_00.exr"), (24, 16));
    std::fs::write(out.join("f_01.exr"), b"not an exr").unwrap();
    // Every EXR is of the wrong size or damaged: all three frames again.
    let text = run("32x20", true);
    assert!(!text.contains("skipped"), "{text}");
    for n in ["f_00.exr", "f_01.exr", "f_02.exr"] {
        assert_eq!(size_of(n), (32, 20), "{n}");
    }
    // Now whole: nothing to render.
    let text = run("32x20", true);
    assert!(text.contains("nothing to render"), "{text}");
}
