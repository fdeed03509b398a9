//! `configs/slurm-render.sh` under a real Slurm: `tests/slurm/localhost.sh` starts munged,
//! slurmctld and slurmd on this host, the script is submitted with `sbatch` for 3 tasks,
//! and its image must equal the in-process render.
//!
//! Needs Debian's `slurm-wlm` and `munge` (`.ci/run` installs them) and root (the daemons
//! run as the caller); where they are missing the test says so on stderr and ends.

use std::path::{Path, PathBuf};
use std::process::Command;

mod common;
use common::{max_diff, read_exr, survey_in, BIN, SIZE};

/// Stops the test's Slurm however the test ends.
struct Slurm(PathBuf);

impl Drop for Slurm {
    fn drop(&mut self) {
        let _ = Command::new(script()).arg("stop").arg(&self.0).status();
    }
}

fn script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/slurm/localhost.sh")
}

fn have(tool: &str) -> bool {
    Command::new("sh")
        .args(["-c", &format!("command -v {tool}")])
        .output()
        .is_ok_and(|o| o.status.success())
}

#[test]
fn slurm_render_sh_under_sbatch_with_3_workers_equals_in_process() {
    let missing: Vec<&str> = ["munged", "slurmctld", "slurmd", "sbatch", "srun"]
        .into_iter()
        .filter(|t| !have(t))
        .collect();
    // CI (`.ci/run`) requires the test to run: a skip there would pass having tested nothing.
    let required = std::env::var("STRATA_REQUIRE_SYSTEM_TESTS").as_deref() == Ok("1");
    if !missing.is_empty() {
        assert!(
            !required,
            "STRATA_REQUIRE_SYSTEM_TESTS=1 but {} not installed",
            missing.join(", ")
        );
        eprintln!(
            "SKIPPED: {} not installed (apt-get install slurm-wlm munge)",
            missing.join(", ")
        );
        return;
    }
    if unsafe { libc::geteuid() } != 0 {
        assert!(
            !required,
            "STRATA_REQUIRE_SYSTEM_TESTS=1 but the test's Slurm daemons need root"
        );
        eprintln!("SKIPPED: the test's Slurm daemons need root");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let slurm_dir = d.join("slurm");
    let o = Command::new(script())
        .arg("start")
        .arg(&slurm_dir)
        .output()
        .unwrap();
    let _slurm = Slurm(slurm_dir.clone());
    assert!(
        o.status.success(),
        "starting Slurm: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let conf = slurm_dir.join("slurm.conf");

    // The script runs `coordinator` and `worker` from PATH: this build's binary, whose
    // `worker` subcommand is the worker.
    let bin = d.join("bin");
    std::fs::create_dir_all(&bin).unwrap();
    std::os::unix::fs::symlink(BIN, bin.join("coordinator")).unwrap();
    std::fs::write(
        bin.join("worker"),
        format!("#!/bin/sh\nexec {BIN} worker \"$@\"\n"),
    )
    .unwrap();
    std::fs::set_permissions(
        bin.join("worker"),
        std::os::unix::fs::PermissionsExt::from_mode(0o755),
    )
    .unwrap();
    // The folder of run folders does not exist yet: the script makes it (private).
    let runs = d.join("runs");

    let scene = survey_in("slurm-survey").join("scene.toml");
    let out = d.join("slurm.png");
    let exr = d.join("slurm.exr");
    let job_out = d.join("job.out");
    let path = format!(
        "{}:{}",
        bin.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let o = Command::new("sbatch")
        .env("SLURM_CONF", &conf)
        .env("PATH", &path)
        .env("STRATA_RUN_DIR", &runs)
        .args(["--wait", "--ntasks=3", "--cpus-per-task=1", "--time=5"])
        .arg(format!("--output={}", job_out.display()))
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/slurm-render.sh"))
        .arg(&scene)
        .arg(&out)
        .arg("--exr")
        .arg(&exr)
        .args(["--size", SIZE, "--set", "render.early_termination=1.0"])
        .output()
        .unwrap();
    let job = std::fs::read_to_string(&job_out).unwrap_or_default();
    assert!(
        o.status.success(),
        "sbatch: {}{}\njob output:\n{job}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(job.contains("3 workers"), "{job}");

    let reference = d.join("in.exr");
    let o = Command::new(BIN)
        .args(["-q", "render", scene.to_str().unwrap(), "-o"])
        .arg(d.join("in.png"))
        .arg("--exr")
        .arg(&reference)
        .args(["--size", SIZE, "--in-process"])
        .args(["--set", "render.early_termination=1.0"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let diff = max_diff(&read_exr(&reference), &read_exr(&exr));
    assert!(diff <= 1e-5, "the Slurm render differs by {diff}:\n{job}");
    // The run folder (secret, fingerprint) is removed when the job ends.
    assert!(std::fs::read_dir(&runs).unwrap().next().is_none());
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&runs).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o700, "{mode:o}");
    }

    // configs/slurm-sequence.sh: an orbit of 4 frames as a job array of 2 tasks, 2 frames
    // each; every frame equals the same orbit rendered in process.
    let seq = d.join("seq");
    let pattern = seq.join("f_%05d.png");
    let array_out = d.join("array-%a.out");
    let o = Command::new("sbatch")
        .env("SLURM_CONF", &conf)
        .env("PATH", &path)
        .args(["--wait", "--array=0-1", "--cpus-per-task=2", "--time=5"])
        .arg(format!("--output={}", array_out.display()))
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/slurm-sequence.sh"))
        .arg(&scene)
        .arg("orbit:4")
        .arg(&pattern)
        .arg("2")
        .output()
        .unwrap();
    let jobs: String = (0..2)
        .map(|t| std::fs::read_to_string(d.join(format!("array-{t}.out"))).unwrap_or_default())
        .collect();
    assert!(
        o.status.success(),
        "sbatch --array: {}{}\njob output:\n{jobs}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    let reference = d.join("ref");
    std::fs::create_dir_all(&reference).unwrap();
    let o = Command::new(BIN)
        .args([
            "-q",
            "render",
            scene.to_str().unwrap(),
            "--in-process",
            "--orbit",
            "4",
        ])
        .arg("-o")
        .arg(reference.join("f_%05d.png"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in 0..4 {
        let name = format!("f_{f:05}.png");
        let (a, b) = (png_rgb(&seq.join(&name)), png_rgb(&reference.join(&name)));
        let worst = a.iter().zip(&b).map(|(x, y)| x.abs_diff(*y)).max().unwrap();
        // Each task runs one worker (2 CPUs / 2), which casts the whole scene as the
        // in-process engine does: the same bytes.
        assert_eq!(worst, 0, "frame {f} differs by {worst} levels:\n{jobs}");
    }
    for t in 0..2 {
        assert!(seq.join(format!("f_task{t}.jsonl")).is_file(), "{jobs}");
    }
}

/// The RGB bytes of a PNG.
fn png_rgb(path: &Path) -> Vec<u8> {
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())),
    ));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    buf
}
