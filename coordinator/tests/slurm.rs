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
    if !missing.is_empty() {
        eprintln!(
            "SKIPPED: {} not installed (apt-get install slurm-wlm munge)",
            missing.join(", ")
        );
        return;
    }
    if unsafe { libc::geteuid() } != 0 {
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
    let runs = d.join("runs");
    std::fs::create_dir_all(&runs).unwrap();

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
}
