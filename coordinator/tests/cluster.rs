//! Distributed rendering end to end: real `coordinator` and worker processes over
//! loopback QUIC. The distributed image must equal the in-process one; bad peers must be
//! refused without taking the run down; a killed worker must fail the frame with an error
//! naming it, within the timeout.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

mod common;
use common::{max_diff, read_exr, read_exr_sized, strip_ansi, survey_in, BIN, SIZE};

/// A small synthetic survey (cube + 3 horizons + scene.toml), generated once per test run.
fn survey() -> &'static Path {
    survey_in("cluster-survey")
}

fn run(args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut c = Command::new(BIN);
    c.arg("-q").args(args);
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().unwrap()
}

/// Renders the survey. Early ray termination is off: a region cannot know the opacity in
/// front of it, so with termination at `t` a sort-last image may differ from the
/// single-process one by up to `1 - t` (checked separately below).
fn render(out: &Path, extra: &[&str], env: &[(&str, &str)]) -> Output {
    render_scene(&survey().join("scene.toml"), out, extra, env)
}

fn render_scene(scene: &Path, out: &Path, extra: &[&str], env: &[(&str, &str)]) -> Output {
    let png = out.with_extension("png");
    let mut args = vec![
        "render",
        scene.to_str().unwrap(),
        "-o",
        png.to_str().unwrap(),
        "--exr",
        out.to_str().unwrap(),
        "--size",
        SIZE,
        "--set",
        "render.early_termination=1.0",
    ];
    args.extend_from_slice(extra);
    run(&args, env)
}

fn bit_identical(a: &[[f32; 4]], b: &[[f32; 4]]) -> bool {
    a.len() == b.len()
        && a.iter()
            .zip(b)
            .all(|(p, q)| (0..4).all(|c| p[c].to_bits() == q[c].to_bits()))
}

/// Generates a synthetic survey of `size` samples into `dir`; returns its scene file.
fn synth_survey(dir: &Path, size: [&str; 3], seed: &str) -> PathBuf {
    let mut args = vec!["synth", "-o", dir.to_str().unwrap(), "--size"];
    args.extend_from_slice(&size);
    args.extend_from_slice(&["--seed", seed]);
    let o = run(&args, &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    dir.join("scene.toml")
}

fn reference() -> &'static Vec<[f32; 4]> {
    static REF: OnceLock<Vec<[f32; 4]>> = OnceLock::new();
    REF.get_or_init(|| {
        let out = survey().join("ref.exr");
        let o = render(&out, &["--in-process"], &[]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        read_exr(&out)
    })
}

#[test]
fn distributed_equals_in_process_for_every_algorithm_and_worker_count() {
    let reference = reference();
    let alpha: f32 = reference.iter().map(|p| p[3]).sum();
    assert!(alpha > 100.0, "the reference image is nearly empty");
    let dir = tempfile::tempdir().unwrap();
    for workers in [1, 2, 3, 4, 7] {
        for algorithm in ["direct-send", "binary-swap", "radix-k", "gather"] {
            let out = dir.path().join(format!("{algorithm}-{workers}.exr"));
            let stats = dir.path().join(format!("{algorithm}-{workers}.jsonl"));
            let set = format!("composite.algorithm={algorithm}");
            let w = workers.to_string();
            let o = render(
                &out,
                &[
                    "--workers",
                    &w,
                    "--set",
                    &set,
                    "--set",
                    "composite.k=2",
                    "--stats",
                    stats.to_str().unwrap(),
                ],
                &[],
            );
            assert!(
                o.status.success(),
                "{algorithm} x{workers}: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            let d = max_diff(reference, &read_exr(&out));
            assert!(
                d <= 1e-5,
                "{algorithm} with {workers} workers differs by {d}"
            );
            // One stats line for the frame, one per worker, then the summary.
            let text = std::fs::read_to_string(&stats).unwrap();
            let mut lines: Vec<serde_json::Value> = text
                .lines()
                .map(|l| serde_json::from_str(l).unwrap())
                .collect();
            assert_eq!(lines.len(), workers + 2);
            assert_eq!(lines.remove(0)["kind"], "frame");
            assert!(lines[..workers].iter().all(|l| l["kind"] == "worker"));
            assert_eq!(lines[workers]["kind"], "summary");
            assert_eq!(lines[workers]["workers"], workers);
            // The first pass's time is the slowest worker's (its map exchange included):
            // with the final round's, the time of every cast the samples count.
            let first = lines[..workers]
                .iter()
                .map(|l| l["prepass_s"].as_f64().unwrap())
                .fold(0.0, f64::max);
            let reported = lines[workers]["first_pass_seconds"].as_f64().unwrap();
            assert!((reported - first).abs() <= 1e-12, "{reported} {first}");
            assert_eq!(
                workers > 1,
                reported > 0.0,
                "occlusion runs with more than one worker"
            );
            // The workers close their peer connections on shutdown and exit at once: a
            // worker that left them to its peer readers waited out its endpoint's 2 s
            // idle wait, which every multi-worker run paid (about 0.01 s now; seven
            // workers on a loaded 2-core machine once took 1.07 s, so the bound sits just
            // under the 2 s it guards against).
            let shutdown = lines[workers]["shutdown_seconds"].as_f64().unwrap();
            assert!(
                shutdown < 1.9,
                "{algorithm} x{workers}: shutting down took {shutdown:.2} s"
            );
            if workers > 1 {
                let sent: u64 = lines[..workers]
                    .iter()
                    .map(|l| l["bytes_sent"].as_u64().unwrap())
                    .sum();
                assert!(sent > 0, "{algorithm} x{workers}: nothing exchanged");
            }
        }
    }
}

/// `cluster.pin_workers`: each local worker runs on CPUs of its own, says which, and the
/// image is the in-process one.
#[test]
fn pinned_workers_run_on_cpus_of_their_own_and_render_the_same_image() {
    let allowed = strata_worker::affinity::allowed().expect("Linux says which CPUs we may use");
    let dir = tempfile::tempdir().unwrap();
    let cpus_of = |name: &str, extra: &[&str]| -> Vec<String> {
        let out = dir.path().join(format!("{name}.exr"));
        let stats = dir.path().join(format!("{name}.jsonl"));
        let args = [
            &["--workers", "2", "--stats", stats.to_str().unwrap()],
            extra,
        ]
        .concat();
        let o = render(&out, &args, &[]);
        assert!(
            o.status.success(),
            "{name}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let d = max_diff(reference(), &read_exr(&out));
        assert!(d <= 1e-5, "{name}: differs from in-process by {d}");
        lines_of_kind(&std::fs::read_to_string(&stats).unwrap(), "worker")
            .iter()
            .map(|w| w["cpus"].as_str().unwrap().to_string())
            .collect()
    };
    // Unbound, each worker may run on every CPU this process may.
    let all = strata_worker::affinity::format_list(&allowed);
    assert_eq!(cpus_of("unbound", &[]), vec![all.clone(), all]);
    // Bound with one thread each: one CPU each, of the allowed ones, and two different
    // CPUs where there are two.
    let bound = cpus_of(
        "bound",
        &[
            "--set",
            "cluster.pin_workers=true",
            "--set",
            "cluster.worker_threads=1",
        ],
    );
    let ids: Vec<usize> = bound
        .iter()
        .map(|c| c.parse().unwrap_or_else(|_| panic!("one CPU, got {c:?}")))
        .collect();
    assert!(
        ids.iter().all(|c| allowed.contains(c)),
        "{ids:?} of {allowed:?}"
    );
    if allowed.len() >= 2 {
        assert_ne!(ids[0], ids[1], "two workers bound to one CPU");
    }
}

#[test]
fn options_that_change_bytes_not_pixels() {
    let reference = reference();
    let dir = tempfile::tempdir().unwrap();
    // Radix-k with explicit factors, no interlacing, two leaves per worker.
    let out = dir.path().join("factors.exr");
    let o = render(
        &out,
        &[
            "--workers",
            "6",
            "--set",
            "composite.k=[3, 2]",
            "--set",
            "composite.interlace=false",
            "--set",
            "cluster.leaves_per_worker=2",
        ],
        &[],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(max_diff(reference, &read_exr(&out)) <= 1e-5);
    // Early ray termination at 0.99 (the default) in every region: the sort-last image
    // stays within 1 - 0.99 of the single-process one, whose rays stop once for all.
    let ert = |name: &str, extra: &[&str]| {
        let out = dir.path().join(name);
        let mut args = extra.to_vec();
        args.extend_from_slice(&["--set", "render.early_termination=0.99"]);
        let o = render(&out, &args, &[]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        read_exr(&out)
    };
    let single = ert("ert1.exr", &["--in-process"]);
    let split = ert("ert4.exr", &["--workers", "4"]);
    let d = max_diff(&single, &split);
    assert!(d <= 0.01 + 1e-5, "early termination: {d}");
    assert!(
        d > 1e-4,
        "early termination had no effect ({d}): is the override applied?"
    );
    // The f16 wire is lossy, but only by half-float rounding.
    let out = dir.path().join("f16.exr");
    let o = render(
        &out,
        &["--workers", "3", "--set", "composite.wire=f16"],
        &[],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let d = max_diff(reference, &read_exr(&out));
    assert!(d <= 4e-3, "f16 differs by {d}");
    // LZ4 on the pieces that travel over QUIC is lossless: the same image bit for bit, in
    // fewer bytes.
    let quic = |name: &str, lz4: bool| {
        let out = dir.path().join(format!("{name}.exr"));
        let stats = dir.path().join(format!("{name}.jsonl"));
        let lz4 = format!("composite.lz4={lz4}");
        let o = render(
            &out,
            &[
                "--workers",
                "3",
                "--set",
                "cluster.transport=quic",
                "--set",
                &lz4,
                "--stats",
                stats.to_str().unwrap(),
            ],
            &[],
        );
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let text = std::fs::read_to_string(&stats).unwrap();
        let summary: serde_json::Value = serde_json::from_str(
            text.lines()
                .find(|l| l.contains("\"kind\":\"summary\""))
                .unwrap(),
        )
        .unwrap();
        let bytes =
            summary["exchange_bytes"].as_u64().unwrap() + summary["gather_bytes"].as_u64().unwrap();
        (read_exr(&out), bytes)
    };
    let (plain, plain_bytes) = quic("quic", false);
    let (packed, packed_bytes) = quic("quic-lz4", true);
    assert!(bit_identical(&plain, &packed), "LZ4 changed a pixel");
    assert!(
        packed_bytes < plain_bytes,
        "LZ4 moved {packed_bytes} bytes, plain {plain_bytes}"
    );
    // Factors that do not multiply to the worker count are refused before any worker starts.
    let o = render(
        &dir.path().join("bad.exr"),
        &["--workers", "4", "--set", "composite.k=[3, 2]"],
        &[],
    );
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("composite"), "{e}");
    assert!(!dir.path().join("bad.png").exists());
}

#[test]
fn shared_memory_and_forced_quic_give_identical_images_and_report_their_transport() {
    let reference = reference();
    let dir = tempfile::tempdir().unwrap();
    let go_with = |name: &str, transport: &str, algorithm: &str, mtu: u16| {
        let out = dir.path().join(format!("{name}.exr"));
        let stats = dir.path().join(format!("{name}.jsonl"));
        let t = format!("cluster.transport={transport}");
        let a = format!("composite.algorithm={algorithm}");
        let m = format!("cluster.quic_mtu={mtu}");
        let o = render(
            &out,
            &[
                "--workers",
                "4",
                "--set",
                &t,
                "--set",
                &a,
                "--set",
                "composite.k=2",
                "--set",
                &m,
                "--stats",
                stats.to_str().unwrap(),
            ],
            &[],
        );
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let text = std::fs::read_to_string(&stats).unwrap();
        let summary: serde_json::Value =
            serde_json::from_str(text.lines().last().unwrap()).unwrap();
        (read_exr(&out), summary)
    };
    let go =
        |name: &str, transport: &str, algorithm: &str| go_with(name, transport, algorithm, 1200);
    let shm_host = strata_net::shm::host_id().is_some();
    for algorithm in ["binary-swap", "radix-k"] {
        let (quic, qs) = go(&format!("quic-{algorithm}"), "quic", algorithm);
        assert_eq!(qs["transport"]["quic_pairs"], 6, "{qs}");
        assert_eq!(qs["transport"]["quic_gather"], 4, "{qs}");
        assert_eq!(qs["exchange_shm_bytes"], 0, "{qs}");
        assert_eq!(qs["canvas_gather"], 0, "{qs}");
        let (auto, s) = go(&format!("auto-{algorithm}"), "auto", algorithm);
        assert!(quic == auto, "{algorithm}: the transport changed pixels");
        // QUIC datagrams starting at 4000 bytes (`cluster.quic_mtu`, as on loopback or
        // jumbo frames): the same pixels.
        let (big, _) = go_with(&format!("quic-mtu-{algorithm}"), "quic", algorithm, 4000);
        assert!(big == quic, "{algorithm}: the datagram size changed pixels");
        assert!(max_diff(reference, &auto) <= 1e-5);
        if shm_host {
            // Four processes on one host: every pair and gather through shared memory,
            // and the same bytes moved as over QUIC (payload and record headers).
            assert_eq!(s["transport"]["shm_pairs"], 6, "{s}");
            assert_eq!(s["transport"]["shm_gather"], 4, "{s}");
            // Every final piece written in place into the coordinator's canvas.
            assert_eq!(s["canvas_gather"], 4, "{s}");
            let shm = s["exchange_shm_bytes"].as_u64().unwrap();
            assert!(
                shm > 0 && shm <= s["exchange_bytes"].as_u64().unwrap(),
                "{s}"
            );
        }
    }
    // A datagram size no path can take is refused before anything starts.
    let o = render(
        &dir.path().join("bad-mtu.exr"),
        &["--workers", "2", "--set", "cluster.quic_mtu=100"],
        &[],
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("cluster.quic_mtu must lie in 1200..=65527"),
        "{err}"
    );
    let o = render(
        &dir.path().join("bad-wait.exr"),
        &["--workers", "2", "--set", "cluster.replacement_wait_s=-1"],
        &[],
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("cluster.replacement_wait_s must be 0 or"),
        "{err}"
    );
    if shm_host {
        // `shm` forced on one host works as `auto` does.
        let (forced, s) = go("shm-forced", "shm", "radix-k");
        assert_eq!(s["transport"]["shm_pairs"], 6, "{s}");
        assert!(max_diff(reference, &forced) <= 1e-5);
    }
}

/// A coordinator in cluster mode (`cluster.spawn = false`) waiting for one worker.
struct Waiting {
    child: Child,
    dir: tempfile::TempDir,
    port: u16,
    fingerprint: String,
}

fn start_waiting_coordinator(workers: usize, extra: &[&str]) -> Waiting {
    start_waiting_coordinator_to(workers, "out.png", extra)
}

/// [`start_waiting_coordinator`], writing its image(s) to `out` in its folder.
fn start_waiting_coordinator_to(workers: usize, out: &str, extra: &[&str]) -> Waiting {
    let dir = tempfile::tempdir().unwrap();
    let secret = dir.path().join("secret");
    std::fs::write(&secret, "correct-horse-battery-staple-42\n").unwrap();
    let fp = dir.path().join("fingerprint");
    let scene = survey().join("scene.toml");
    let sets = [
        "cluster.spawn=false".to_string(),
        format!("cluster.secret_file={:?}", secret.display().to_string()),
        format!("cluster.fingerprint_file={:?}", fp.display().to_string()),
        "cluster.connect_timeout_s=60".to_string(),
        // The hand-driven workers of these tests speak the exchange, not occlusion.
        "cluster.occlusion=false".to_string(),
    ];
    let mut c = Command::new(BIN);
    c.args(["render", scene.to_str().unwrap(), "-o"])
        .arg(dir.path().join(out))
        .args(["--size", SIZE, "--workers", &workers.to_string()]);
    for s in &sets {
        c.args(["--set", s]);
    }
    c.args(extra).stdout(Stdio::piped()).stderr(Stdio::piped());
    let child = c.spawn().unwrap();
    let t = Instant::now();
    while !fp.exists() {
        assert!(t.elapsed() < Duration::from_secs(60), "no fingerprint file");
        std::thread::sleep(Duration::from_millis(20));
    }
    let fingerprint = std::fs::read_to_string(&fp).unwrap().trim().to_string();
    // The port is in the log line "coordinator listening listen=127.0.0.1:PORT".
    let mut child = child;
    let stderr = child.stderr.take().unwrap();
    let mut reader = BufReader::new(stderr);
    let mut port = 0;
    let mut line = String::new();
    while port == 0 {
        line.clear();
        assert!(
            reader.read_line(&mut line).unwrap() > 0,
            "coordinator ended"
        );
        let plain = strip_ansi(&line);
        if let Some(i) = plain.find("listen=127.0.0.1:") {
            let rest = &plain[i + "listen=127.0.0.1:".len()..];
            port = rest
                .split(|c: char| !c.is_ascii_digit())
                .next()
                .unwrap()
                .parse()
                .unwrap();
        }
    }
    // Keep draining the log so the coordinator never blocks on a full pipe.
    let log = dir.path().join("coordinator.log");
    let log2 = log.clone();
    std::thread::spawn(move || {
        use std::io::Write;
        let mut f = std::fs::File::create(log2).unwrap();
        for l in reader.lines() {
            let Ok(l) = l else { break };
            writeln!(f, "{}", strip_ansi(&l)).unwrap();
        }
    });
    Waiting {
        child,
        dir,
        port,
        fingerprint,
    }
}

fn worker(w: &Waiting, fingerprint: &str, secret: &str) -> Output {
    Command::new(BIN)
        .args(["worker", "--connect"])
        .arg(format!("127.0.0.1:{}", w.port))
        .args(["--fingerprint", fingerprint, "--connect-timeout-s", "10"])
        .env("STRATA_SECRET", secret)
        .output()
        .unwrap()
}

#[test]
fn bad_peers_are_refused_and_the_run_goes_on() {
    let mut w = start_waiting_coordinator(1, &[]);
    let fp = w.fingerprint.clone();

    // 1. A worker that pins another certificate refuses the coordinator itself.
    let wrong_fp = "ab".repeat(32);
    let o = worker(&w, &wrong_fp, "correct-horse-battery-staple-42");
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("not the pinned"), "{e}");
    // Only the start of the pinned value is shown (it could be a secret pinned by mistake).
    assert!(
        e.contains("\"abababab\"… (64 characters)") && !e.contains(&wrong_fp),
        "{e}"
    );

    // 2. The wrong secret is refused by the coordinator, and the worker says so.
    let o = worker(&w, &fp, "not-the-secret-of-this-run");
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("wrong shared secret"), "{e}");

    // 3. An oversized frame and a malformed one: refused by the header, connection closed.
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let pinned = strata_net::tls::parse_fingerprint(&fp).unwrap();
    let addr: std::net::SocketAddr = format!("127.0.0.1:{}", w.port).parse().unwrap();
    rt.block_on(async {
        for (meta_len, body) in [(u32::MAX, vec![]), (40u32, vec![0xffu8; 40])] {
            let (_id, _ep, conn) = dial(addr, pinned).await;
            let (mut send, mut recv) = conn.open_bi().await.unwrap();
            let header = strata_common::wire::encode_header(meta_len, 0);
            send.write_all(&header).await.unwrap();
            send.write_all(&body).await.unwrap();
            // The coordinator closes the connection: reading ends with an error, promptly.
            let r = tokio::time::timeout(Duration::from_secs(15), recv.read_to_end(1 << 20)).await;
            assert!(matches!(r, Ok(Err(_))), "connection not closed: {r:?}");
        }
    });

    // 3b. The right secret, but a hello naming another certificate than the one presented
    //     (its peers would pin the wrong one), and a client that presents none.
    rt.block_on(async {
        let other = strata_net::Identity::generate().unwrap();
        let (_id, ep, conn) = dial(addr, pinned).await;
        let (mut send, mut recv) = conn.open_bi().await.unwrap();
        let hello = strata_common::wire::encode_meta(&strata_common::wire::WorkerMsg::Hello {
            secret: strata_common::wire::Secret(b"correct-horse-battery-staple-42".to_vec()),
            name: "impostor".into(),
            pid: 1,
            fingerprint: other.fingerprint,
            host: None,
        });
        strata_net::frame::write_frame(&mut send, &hello, &[])
            .await
            .unwrap();
        let f = tokio::time::timeout(
            Duration::from_secs(15),
            strata_net::frame::read_frame(&mut recv, &strata_common::wire::Limits::HANDSHAKE),
        )
        .await
        .unwrap()
        .unwrap();
        match strata_common::wire::decode_meta::<strata_common::wire::CoordMsg>(&f.meta) {
            Ok(strata_common::wire::CoordMsg::Refused { reason }) => {
                assert!(reason.contains("not the one the hello names"), "{reason}")
            }
            other => panic!("expected a refusal, got {other:?}"),
        }
        // Without a certificate the handshake itself fails.
        let net = strata_net::NetConfig::default();
        let bare =
            strata_net::transport::connect(&ep, addr, pinned, &net, Duration::from_secs(10)).await;
        if let Ok(conn) = bare {
            // TLS 1.3: the client may finish first; the server then closes the connection.
            let r = tokio::time::timeout(Duration::from_secs(15), conn.closed()).await;
            assert!(r.is_ok(), "a client without a certificate was kept");
        }
    });

    // 4. A good worker is still welcome and the render completes.
    let o = worker(&w, &fp, "correct-horse-battery-staple-42");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let status = w.child.wait().unwrap();
    assert!(status.success());
    assert!(w.dir.path().join("out.png").exists());
    // The log is drained by a thread: wait for it to catch up with the ended coordinator.
    let read_log = || std::fs::read_to_string(w.dir.path().join("coordinator.log")).unwrap();
    let t = Instant::now();
    while read_log().matches("refused a connection").count() < 6
        && t.elapsed() < Duration::from_secs(10)
    {
        std::thread::sleep(Duration::from_millis(100));
    }
    let log = read_log();
    assert!(log.contains("wrong shared secret"), "{log}");
    // One refusal each: the worker that pinned another certificate (its handshake ends),
    // the wrong secret, the oversized frame, the malformed one, the hello naming another
    // certificate and the client without one.
    assert_eq!(log.matches("refused a connection").count(), 6, "{log}");
    assert!(log.contains("not the one the hello names"), "{log}");
}

#[test]
fn a_killed_worker_fails_the_frame_with_an_error_naming_it_when_asked_to_fail() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("killed.exr");
    let t = Instant::now();
    let o = render(
        &out,
        &[
            "--workers",
            "3",
            "--set",
            "cluster.idle_timeout_s=3",
            "--set",
            "cluster.on_worker_loss=\"fail\"",
        ],
        &[
            ("STRATA_TEST_FAULT", "1:kill:exchange"),
            ("RUST_LOG", "info"),
        ],
    );
    let took = t.elapsed();
    assert!(!o.status.success());
    let e = strip_ansi(&String::from_utf8_lossy(&o.stderr));
    let last = e.lines().last().unwrap_or_default();
    assert!(last.contains("worker 1"), "{last}");
    assert!(
        last.contains("killed by signal 9") || last.contains("disconnected"),
        "{last}"
    );
    assert!(took < Duration::from_secs(60), "took {took:?}");
    assert!(!out.exists() && !out.with_extension("png").exists());
    // No orphans: every worker pid the coordinator logged is gone (and all three were
    // logged, so the check cannot pass for want of lines).
    std::thread::sleep(Duration::from_millis(500));
    let joined: Vec<&str> = e.lines().filter(|l| l.contains("worker joined")).collect();
    assert_eq!(joined.len(), 3, "{e}");
    for l in joined {
        let pid = l
            .split("pid=")
            .nth(1)
            .and_then(|r| r.split_whitespace().next())
            .unwrap();
        let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
        // Gone, or a zombie awaiting its (already gone) parent's reaper.
        assert!(
            stat.is_empty() || stat.split_whitespace().nth(2) == Some("Z"),
            "worker {pid} still running: {stat}"
        );
    }
}

/// A run's `--stats` text and its summary's `lost_workers`.
fn lost_workers(stats: &Path) -> (String, Vec<serde_json::Value>) {
    let text = std::fs::read_to_string(stats).unwrap();
    let summary: serde_json::Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
    let lost = summary["lost_workers"].as_array().unwrap().clone();
    (text, lost)
}

/// Renders the survey on `workers` workers (3 unless `extra` says otherwise) while worker 1
/// SIGKILLs or SIGSTOPs itself at `phase` (`STRATA_TEST_FAULT`), and checks that the frame
/// equals the in-process one and that the stats tell the loss: rank 1, `lost_phase`, why,
/// how long the recovery took, who renders what now (every other rank, each with leaves),
/// and the frame stats of the workers left.
fn check_recovery(
    phase: &str,
    signal: &str,
    lost_phase: &str,
    said: &str,
    workers: u32,
    extra: &[&str],
) {
    let dir = tempfile::tempdir().unwrap();
    let name = format!("{signal}-{phase}");
    let out = dir.path().join(format!("{name}.exr"));
    let stats = dir.path().join(format!("{name}.jsonl"));
    let fault = format!("1:{signal}:{phase}");
    let t = Instant::now();
    let n = workers.to_string();
    let mut args = vec![
        "--workers",
        &n,
        "--set",
        "cluster.idle_timeout_s=2",
        "--stats",
        stats.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    let o = render(&out, &args, &[("STRATA_TEST_FAULT", &fault)]);
    let took = t.elapsed();
    assert!(
        o.status.success(),
        "{name}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    // Detection by exit or the idle timeout, not by a deadline of the frame or set-up.
    assert!(took < Duration::from_secs(30), "{name}: took {took:?}");
    let d = max_diff(reference(), &read_exr(&out));
    assert!(d <= 1e-5, "{name}: the recovered frame differs by {d}");
    let (text, lost) = lost_workers(&stats);
    assert_eq!(lost.len(), 1, "{name}: {text}");
    assert_eq!(lost[0]["rank"], 1, "{name}: {text}");
    assert_eq!(lost[0]["phase"], lost_phase, "{name}: {text}");
    assert!(
        lost[0]["recovery_s"].as_f64().unwrap() > 0.0,
        "{name}: {text}"
    );
    let assignment = lost[0]["assignment"].as_array().unwrap();
    let ranks: Vec<u64> = assignment
        .iter()
        .map(|a| a["rank"].as_u64().unwrap())
        .collect();
    let left: Vec<u64> = (0..workers as u64).filter(|&r| r != 1).collect();
    assert_eq!(ranks, left, "{name}: {text}");
    assert!(
        assignment
            .iter()
            .all(|a| !a["leaves"].as_array().unwrap().is_empty()),
        "{name}: {text}"
    );
    assert_eq!(
        text.matches("\"kind\":\"worker\"").count(),
        left.len(),
        "{name}: {text}"
    );
    // The summary's workers are the last frame's, as its compositing figures are.
    let summary: serde_json::Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
    assert_eq!(summary["workers"], left.len(), "{name}: {text}");
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains(said), "{name}: {stdout}");
    if lost_phase == "set-up" {
        // The transport report counts the workers set up, not the one given up on.
        let summary: serde_json::Value =
            serde_json::from_str(text.lines().last().unwrap()).unwrap();
        let t = &summary["transport"];
        let n = left.len() as u64;
        let count = |k: &str| t[k].as_u64().unwrap();
        assert_eq!(
            count("shm_pairs") + count("quic_pairs"),
            n * (n - 1) / 2,
            "{name}: {t}"
        );
        assert_eq!(count("shm_gather") + count("quic_gather"), n, "{name}: {t}");
    }
    if signal == "kill" {
        assert!(
            lost[0]["reason"]
                .as_str()
                .unwrap()
                .contains("killed by signal 9"),
            "{name}: {text}"
        );
    }
}

#[test]
fn a_worker_killed_or_stopped_at_any_phase_of_a_frame_costs_a_re_render() {
    for phase in ["render", "exchange", "round", "gather"] {
        for signal in ["kill", "stop"] {
            check_recovery(phase, signal, "frame", "re-rendered without it", 3, &[]);
        }
    }
    // A later exchange round: binary swap over 4 workers has two; worker 1 goes with its
    // second round's pieces sent.
    for signal in ["kill", "stop"] {
        check_recovery(
            "round1",
            signal,
            "frame",
            "re-rendered without it",
            4,
            &["--set", "composite.algorithm=binary-swap"],
        );
    }
    // Exact radix factors for four workers cannot plan the three left: the re-render takes
    // automatic factors up to the largest of them (it used to fail on every worker, and the
    // run with it, naming a healthy one).
    check_recovery(
        "render",
        "kill",
        "frame",
        "re-rendered without it",
        4,
        &[
            "--set",
            "composite.algorithm=radix-k",
            "--set",
            "composite.k=[2, 2]",
        ],
    );
}

#[test]
fn a_worker_killed_or_stopped_during_set_up_is_left_out_and_the_frame_is_correct() {
    // `setup`: before it dials its peers (they cannot mesh); `ready`: meshed, before it
    // says it is ready. Either way the two workers left are set up again without it.
    for phase in ["setup", "ready"] {
        for signal in ["kill", "stop"] {
            check_recovery(phase, signal, "set-up", "during set-up", 3, &[]);
        }
    }
    let dir = tempfile::tempdir().unwrap();
    // Asked to fail, a loss during set-up ends the run with an error naming the worker.
    let out = dir.path().join("fail.exr");
    let o = render(
        &out,
        &["--workers", "3", "--set", "cluster.on_worker_loss=\"fail\""],
        &[("STRATA_TEST_FAULT", "1:kill:setup")],
    );
    assert!(!o.status.success());
    let e = strip_ansi(&String::from_utf8_lossy(&o.stderr));
    let last = e.lines().last().unwrap_or_default();
    assert!(
        last.contains("worker 1") && last.contains("during set-up") && last.contains("signal 9"),
        "{last}"
    );
    assert!(!out.exists());
}

#[test]
fn a_hung_worker_is_given_up_on_and_the_sequence_goes_on_without_it() {
    let dir = tempfile::tempdir().unwrap();
    let scene = survey().join("scene.toml");
    let (_, _) = orbit_run(&scene, dir.path(), "in", 3, &["--in-process"]);
    // Worker 2 stops itself (SIGSTOP) before its first exchange: alive, silent. Its
    // connections go quiet; the idle timeout gives it up, and frames 0..3 complete with
    // the two workers left.
    let out = dir.path().join("hung_%03d.exr");
    let stats = dir.path().join("hung.jsonl");
    let o = render_scene(
        &scene,
        &out,
        &[
            "--orbit",
            "3",
            "--workers",
            "3",
            "--set",
            "cluster.idle_timeout_s=3",
            "--stats",
            stats.to_str().unwrap(),
        ],
        &[
            ("STRATA_TEST_FAULT", "2:stop:exchange"),
            ("RUST_LOG", "warn,strata_coordinator::cluster=debug"),
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    // The stopped worker was killed when it was given up on, while the run went on (a
    // stopped process does not exit by itself; at the coordinator's exit it would die
    // unseen).
    assert!(
        err.lines()
            .any(|l| l.contains("a worker given up on has exited") && l.contains("signal 9")),
        "{err}"
    );
    for i in 0..3 {
        let a = read_exr(&dir.path().join(format!("in_{i:03}.exr")));
        let b = read_exr(&dir.path().join(format!("hung_{i:03}.exr")));
        let d = max_diff(&a, &b);
        assert!(d <= 1e-5, "frame {i} differs by {d}");
    }
    let (text, lost) = lost_workers(&stats);
    assert_eq!(lost.len(), 1, "{text}");
    assert_eq!(lost[0]["rank"], 2, "{text}");
    // Frame 0 by two workers after the loss, and so are frames 1 and 2.
    assert_eq!(text.matches("\"kind\":\"worker\"").count(), 6, "{text}");
}

/// The worker in front renders slowly, reaching the exchange past its own deadline while
/// the workers behind it were held on their occlusion maps until it reported: it waits a
/// grace window for their pieces instead of timing out at once and blaming them (the
/// coordinator had given up the healthy workers and kept the slow one). The frame
/// completes, late but within the coordinator's timeout, and nobody is lost.
#[test]
fn a_slow_front_worker_does_not_blame_the_peers_held_behind_it() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("slow.exr");
    let stats = dir.path().join("slow.jsonl");
    // Frame timeout 4 s: the workers' 3.2 s, their grace 0.2 s. The front worker sleeps
    // 3.3 s before rendering.
    let o = render(
        &out,
        &[
            "--workers",
            "3",
            "--set",
            "cluster.frame_timeout_s=4",
            "--stats",
            stats.to_str().unwrap(),
        ],
        &[("STRATA_TEST_FAULT", "@0:slow3300:render")],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let d = max_diff(reference(), &read_exr(&out));
    assert!(d <= 1e-5, "the frame differs by {d}");
    let (text, lost) = lost_workers(&stats);
    assert!(lost.is_empty(), "{text}");
    assert_eq!(text.matches("\"kind\":\"worker\"").count(), 3, "{text}");
}

#[test]
fn a_worker_stuck_mid_frame_is_blamed_by_its_peers_before_the_frame_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let scene = survey().join("scene.toml");
    let (_, _) = orbit_run(&scene, dir.path(), "in", 2, &["--in-process"]);
    // Worker 2's frame thread blocks before it renders frame 0 (as on a read that never
    // returns): its process and connections live on, so neither the watchdog nor a lost
    // connection gives it up. The survivors wait for its pieces until their own frame
    // timeout, shorter than the coordinator's, and blame it; without occlusion nothing
    // else tells the coordinator who hangs (it had blamed all three and ended the run).
    // With occlusion (the default) each rank in turn, so that one hangs in the middle of
    // the order: the workers behind it wait for their maps, and the peers that miss their
    // pieces must not get them given up too.
    let runs = [("false", 2), ("true", 0), ("true", 1), ("true", 2)];
    for (occlusion, hung) in runs {
        let fault = format!("{hung}:hang:render");
        let out = dir
            .path()
            .join(format!("stuck_{occlusion}_{hung}_%03d.exr"));
        let stats = dir.path().join(format!("stuck_{occlusion}_{hung}.jsonl"));
        let o = render_scene(
            &scene,
            &out,
            &[
                "--orbit",
                "2",
                "--workers",
                "3",
                "--set",
                "cluster.frame_timeout_s=8",
                "--set",
                &format!("cluster.occlusion={occlusion}"),
                "--stats",
                stats.to_str().unwrap(),
            ],
            &[("STRATA_TEST_FAULT", &fault)],
        );
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            o.status.success(),
            "occlusion {occlusion}, rank {hung}: {err}"
        );
        for i in 0..2 {
            let a = read_exr(&dir.path().join(format!("in_{i:03}.exr")));
            let b = read_exr(
                &dir.path()
                    .join(format!("stuck_{occlusion}_{hung}_{i:03}.exr")),
            );
            let d = max_diff(&a, &b);
            assert!(
                d <= 1e-5,
                "occlusion {occlusion}, rank {hung}: frame {i} differs by {d}"
            );
        }
        let (text, lost) = lost_workers(&stats);
        assert_eq!(lost.len(), 1, "rank {hung}: {text}");
        assert_eq!(lost[0]["rank"], hung, "{text}");
    }
}

/// The checks of a 4-frame orbit on 2 workers where worker 1 was lost in frame 0 and a
/// replacement joined at frame 1: every frame (`out(i)`) equals the in-process one in
/// `refs`, the summary lists one loss and one joiner (rank 2, frame 1, assignment 0 and 2),
/// frame 0 was rendered by worker 0 alone and frames 1..3 by workers 0 and 2.
fn check_replacement(stats: &str, refs: &Path, out: impl Fn(usize) -> PathBuf) {
    same_as_in_process(refs, 4, out);
    let summary: serde_json::Value = serde_json::from_str(stats.lines().last().unwrap()).unwrap();
    let joined = summary["joined_workers"].as_array().unwrap();
    assert_eq!(joined.len(), 1, "{stats}");
    assert_eq!(joined[0]["rank"], 2, "{stats}");
    assert_eq!(joined[0]["frame"], 1, "{stats}");
    let ranks: Vec<u64> = joined[0]["assignment"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["rank"].as_u64().unwrap())
        .collect();
    assert_eq!(ranks, [0, 2], "{stats}");
    assert_eq!(
        summary["lost_workers"].as_array().unwrap().len(),
        1,
        "{stats}"
    );
    // Frame 0 by worker 0 alone; frames 1..3 by workers 0 and 2.
    assert_eq!(ranks_in_frame(stats, 0), [0], "{stats}");
    for f in 1..4 {
        assert_eq!(ranks_in_frame(stats, f), [0, 2], "frame {f}: {stats}");
    }
}

/// The ranks whose worker stats the stats file lists for frame `f`.
fn ranks_in_frame(stats: &str, f: u64) -> Vec<u64> {
    stats
        .lines()
        .filter(|l| l.contains("\"kind\":\"worker\""))
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .filter(|v| v["frame"] == f)
        .map(|v| v["rank"].as_u64().unwrap())
        .collect()
}

#[test]
fn a_lost_local_worker_is_replaced_by_a_spawned_one_with_cluster_respawn() {
    let scene = survey().join("scene.toml");
    let refs = tempfile::tempdir().unwrap();
    let (_, _) = orbit_run(&scene, refs.path(), "in", 4, &["--in-process"]);
    // Local mode, 2 workers: worker 1 kills itself in frame 0's exchange, frame 0 is
    // re-rendered by worker 0 alone, and the coordinator spawns a replacement that takes
    // load from frame 1 on.
    let dir = tempfile::tempdir().unwrap();
    // An orbit of `frames`, `faults` (worker 1 killing itself in frame 0's
    // exchange, and more); returns the stats and the log.
    let run_with = |name: &str, frames: &str, extra: &[&str], faults: &str| {
        let stats = dir.path().join(format!("{name}.jsonl"));
        let mut args = vec![
            "--orbit",
            frames,
            "--stats",
            stats.to_str().unwrap(),
            "--set",
            "cluster.idle_timeout_s=2",
        ];
        args.extend_from_slice(extra);
        let o = render_scene(
            &scene,
            &dir.path().join(format!("{name}_%03d.exr")),
            &args,
            &[("STRATA_TEST_FAULT", faults), ("RUST_LOG", "info")],
        );
        let log = strip_ansi(&String::from_utf8_lossy(&o.stderr));
        assert!(o.status.success(), "{name}: {log}");
        (std::fs::read_to_string(&stats).unwrap(), log)
    };
    let run = |name: &str, frames: &str, extra: &[&str]| {
        let args = [&["--workers", "2"], extra].concat();
        run_with(name, frames, &args, "1:kill:exchange")
    };
    let (stats, log) = run("respawn", "4", &["--set", "cluster.respawn=1"]);
    assert!(log.contains("spawned a replacement worker"), "{log}");
    check_replacement(&stats, refs.path(), |i| {
        dir.path().join(format!("respawn_{i:03}.exr"))
    });
    // Without `cluster.respawn` the run goes on with worker 0 alone.
    let (stats, _) = run("alone", "2", &[]);
    let summary: serde_json::Value = serde_json::from_str(stats.lines().last().unwrap()).unwrap();
    assert!(
        summary["joined_workers"].as_array().unwrap().is_empty(),
        "{stats}"
    );
    assert_eq!(stats.matches("\"kind\":\"worker\"").count(), 2, "{stats}");
    // A replacement that dies in its set-up is given up on, never the run, and the next
    // replacement takes its place: frames 0 and 1 by worker 0 alone, 2 and 3 by workers 0
    // and 3, every frame as in-process.
    let (stats, log) = run_with(
        "twice",
        "4",
        &["--workers", "2", "--set", "cluster.respawn=2"],
        "1:kill:exchange,2:kill:setup",
    );
    for i in 0..4 {
        let d = max_diff(
            &read_exr(&refs.path().join(format!("in_{i:03}.exr"))),
            &read_exr(&dir.path().join(format!("twice_{i:03}.exr"))),
        );
        assert!(d <= 1e-5, "frame {i} differs by {d}");
    }
    assert_eq!(
        log.matches("spawned a replacement worker").count(),
        2,
        "{log}"
    );
    let summary: serde_json::Value = serde_json::from_str(stats.lines().last().unwrap()).unwrap();
    let lost: Vec<u64> = summary["lost_workers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["rank"].as_u64().unwrap())
        .collect();
    assert_eq!(lost, [1, 2], "{stats}");
    let joined = summary["joined_workers"].as_array().unwrap();
    assert_eq!(joined.len(), 1, "{stats}");
    assert_eq!(joined[0]["rank"], 3, "{stats}");
    assert_eq!(joined[0]["frame"], 2, "{stats}");
    for (f, want) in [(0, vec![0]), (1, vec![0]), (2, vec![0, 3]), (3, vec![0, 3])] {
        assert_eq!(ranks_in_frame(&stats, f), want, "frame {f}: {stats}");
    }
    // Two workers of three lost in one frame and one replacement allowed: frame 1 waits
    // for the one spawned, not for the run to be full again (`connect_timeout_s`).
    let t = Instant::now();
    let (stats, _) = run_with(
        "two",
        "2",
        &[
            "--workers",
            "3",
            "--set",
            "cluster.respawn=1",
            "--set",
            "cluster.connect_timeout_s=120",
        ],
        "1:kill:exchange,2:kill:exchange",
    );
    assert!(
        t.elapsed() < Duration::from_secs(60),
        "took {:?}",
        t.elapsed()
    );
    assert_eq!(ranks_in_frame(&stats, 0), [0], "{stats}");
    assert_eq!(ranks_in_frame(&stats, 1), [0, 3], "{stats}");
    // A worker stopped in set-up (found lost by the idle timeout, 2 s in) is replaced
    // before frame 0: the replacement's set-up does not rewrite the loss's recovery time,
    // measured from the first set-up's start (it once came out as 0.03 − 2.09 s).
    let (stats, _) = run_with(
        "setup",
        "1",
        &["--workers", "2", "--set", "cluster.respawn=1"],
        "1:stop:setup",
    );
    let summary: serde_json::Value = serde_json::from_str(stats.lines().last().unwrap()).unwrap();
    let lost = summary["lost_workers"].as_array().unwrap();
    assert_eq!(lost.len(), 1, "{stats}");
    assert_eq!(lost[0]["phase"], "set-up", "{stats}");
    let detected = lost[0]["detected_after_s"].as_f64().unwrap();
    let recovery = lost[0]["recovery_s"].as_f64().unwrap();
    assert!(detected > 1.0 && recovery > 0.0, "{stats}");
    assert_eq!(
        summary["joined_workers"].as_array().unwrap().len(),
        1,
        "{stats}"
    );
    assert_eq!(ranks_in_frame(&stats, 0), [0, 2], "{stats}");
}

/// Frames `0..frames` (`out(i)`) equal the in-process ones in `refs` (`in_%03d.exr`).
fn same_as_in_process(refs: &Path, frames: usize, out: impl Fn(usize) -> PathBuf) {
    for i in 0..frames {
        let d = max_diff(
            &read_exr(&refs.join(format!("in_{i:03}.exr"))),
            &read_exr(&out(i)),
        );
        assert!(d <= 1e-5, "frame {i} differs by {d}");
    }
}

/// The in-process orbit of `frames` into a new folder (`in_%03d.exr`), and a waiting
/// cluster-mode coordinator for 2 workers rendering the same orbit into another
/// (`{name}_%03d.exr`, stats `{name}.jsonl`), which after a loss waits up to 30 s for a
/// replacement.
fn replacement_run(name: &str, frames: u32) -> (tempfile::TempDir, tempfile::TempDir, Waiting) {
    let scene = survey().join("scene.toml");
    let refs = tempfile::tempdir().unwrap();
    let (_, _) = orbit_run(&scene, refs.path(), "in", frames, &["--in-process"]);
    let outd = tempfile::tempdir().unwrap();
    let at = |n: &str| outd.path().join(n).display().to_string();
    let w = start_waiting_coordinator_to(
        2,
        &at(&format!("{name}_%03d.png")),
        &[
            "--orbit",
            &frames.to_string(),
            "--exr",
            &at(&format!("{name}_%03d.exr")),
            "--stats",
            &at(&format!("{name}.jsonl")),
            "--set",
            "render.early_termination=1.0",
            "--set",
            "cluster.idle_timeout_s=2",
            "--set",
            "cluster.replacement_wait_s=30",
        ],
    );
    (refs, outd, w)
}

/// A worker started by hand for the waiting coordinator `w`, with `STRATA_TEST_FAULT` set
/// to `fault`.
fn faulty_worker(w: &Waiting, fault: Option<&str>) -> Child {
    let mut c = Command::new(BIN);
    c.args(["worker", "--connect"])
        .arg(format!("127.0.0.1:{}", w.port))
        .args(["--fingerprint", &w.fingerprint, "--connect-timeout-s", "20"])
        .env("STRATA_SECRET", "correct-horse-battery-staple-42")
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    if let Some(f) = fault {
        c.env("STRATA_TEST_FAULT", f);
    }
    c.spawn().unwrap()
}

/// Two workers for `w` (waiting for 2), the second (rank 1) killing itself in frame 0's
/// exchange; returns once the coordinator re-renders that frame without it.
fn two_workers_losing_one(w: &Waiting) -> (Child, Child) {
    let log = w.dir.path().join("coordinator.log");
    let a = faulty_worker(w, Some("1:kill:exchange"));
    wait_for_log(&log, "worker joined rank=0");
    let b = faulty_worker(w, Some("1:kill:exchange"));
    wait_for_log(&log, "re-rendering the frame without worker 1");
    (a, b)
}

#[test]
fn a_newcomer_announcing_a_bad_segment_is_given_up_on_not_the_run() {
    use strata_common::wire::WorkerMsg;
    if strata_net::shm::host_id().is_none() {
        eprintln!("skipped: this host has no /dev/shm");
        return;
    }
    // Cluster mode, 2 workers: worker 1 dies in frame 0, and the replacement frame 1
    // waits for is a fake that announces a shared-memory segment that does not exist.
    let (refs, outd, w) = replacement_run("new", 2);
    let at = |n: &str| outd.path().join(n).display().to_string();
    let (mut a, mut b) = two_workers_losing_one(&w);
    runtime().block_on(async {
        let (_ep, _conn, mut send, _recv, setup) = fake_worker(&w).await;
        assert!(setup.shm_gather, "the newcomer is on this host");
        // As a real worker does: which set-up it answers (a later one than the first).
        let meshing = WorkerMsg::Meshing {
            attempt: setup.attempt,
        };
        strata_net::write_frame(&mut send, &strata_common::wire::encode_meta(&meshing), &[])
            .await
            .unwrap();
        let msg = WorkerMsg::ShmSegment {
            name: format!("strata-shm-{}", "0f".repeat(16)),
            pid: std::process::id(),
            fd: 1 << 20,
        };
        say_then_linger(&mut send, &msg).await;
    });
    let (status, log) = finish(w);
    assert!(status.success(), "{log}");
    for p in [&mut a, &mut b] {
        let _ = p.wait();
    }
    // Both frames as in-process, by worker 0 alone.
    same_as_in_process(refs.path(), 2, |i| {
        outd.path().join(format!("new_{i:03}.exr"))
    });
    let stats = std::fs::read_to_string(at("new.jsonl")).unwrap();
    for f in 0..2 {
        assert_eq!(ranks_in_frame(&stats, f), [0], "frame {f}: {stats}");
    }
    let summary: serde_json::Value = serde_json::from_str(stats.lines().last().unwrap()).unwrap();
    assert!(
        summary["joined_workers"].as_array().unwrap().is_empty(),
        "{stats}"
    );
    let lost = summary["lost_workers"].as_array().unwrap();
    let ranks: Vec<u64> = lost.iter().map(|l| l["rank"].as_u64().unwrap()).collect();
    assert_eq!(ranks, [1, 2], "{stats}");
    assert!(
        lost[1]["worker"].as_str().unwrap().contains("fake")
            && lost[1]["reason"]
                .as_str()
                .unwrap()
                .contains("shared-memory segment"),
        "{stats}"
    );
}

#[test]
fn a_replacement_worker_joins_a_running_sequence_and_takes_load() {
    // Cluster mode, 2 workers: worker 1 kills itself in frame 0's exchange, frame 0 is
    // re-rendered by worker 0 alone, and frame 1 waits for a replacement.
    let (refs, outd, w) = replacement_run("rep", 4);
    let at = |n: &str| outd.path().join(n).display().to_string();
    let log = w.dir.path().join("coordinator.log");
    let (mut a, mut b) = two_workers_losing_one(&w);
    let mut c = faulty_worker(&w, None);
    let mut w = w;
    let status = w.child.wait().unwrap();
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(status.success(), "{text}");
    for p in [&mut a, &mut b, &mut c] {
        let _ = p.wait();
    }
    let stats = std::fs::read_to_string(at("rep.jsonl")).unwrap();
    check_replacement(&stats, refs.path(), |i| {
        PathBuf::from(at(&format!("rep_{i:03}.exr")))
    });
    assert!(
        text.contains("worker joined the running sequence"),
        "{text}"
    );
}

#[test]
fn gpu_workers_equal_the_in_process_cpu_image() {
    // Three worker processes, each casting the survey's volume and horizons on its own wgpu
    // device (lavapipe in CI), composite to the single-process CPU image. Skipped without an
    // adapter unless one is required.
    if strata_worker::gpu::list_adapters().is_empty() {
        assert_ne!(
            std::env::var("STRATA_REQUIRE_GPU_ADAPTER").as_deref(),
            Ok("1"),
            "STRATA_REQUIRE_GPU_ADAPTER=1 but wgpu finds no adapter"
        );
        eprintln!("NOTICE: skipped, no wgpu adapter");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let scene = survey().join("scene.toml");
    let go = |name: &str, extra: &[&str]| {
        let out = dir.path().join(format!("{name}.exr"));
        let stats = out.with_extension("jsonl");
        let mut args = vec!["--stats", stats.to_str().unwrap()];
        args.extend_from_slice(extra);
        let o = render_scene(&scene, &out, &args, &[]);
        assert!(
            o.status.success(),
            "{name}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        (read_exr(&out), std::fs::read_to_string(&stats).unwrap())
    };
    let (cpu, cpu_stats) = go("cpu", &["--in-process", "--set", "render.backend=cpu"]);
    assert!(cpu_stats.contains("\"backend\":\"cpu"), "{cpu_stats}");
    let (gpu, gpu_stats) = go("gpu", &["--workers", "3", "--set", "render.backend=gpu"]);
    let d = max_diff(&cpu, &gpu);
    assert!(
        d <= 1e-4,
        "3 GPU workers against the in-process CPU image: {d}"
    );
    let alpha: f32 = cpu.iter().map(|p| p[3]).sum();
    assert!(alpha > 100.0, "the image shows the data");
    let workers = gpu_stats
        .lines()
        .filter(|l| l.contains("\"kind\":\"worker\""))
        .collect::<Vec<_>>();
    assert_eq!(workers.len(), 3, "{gpu_stats}");
    for l in workers {
        assert!(l.contains("\"backend\":\"gpu: "), "{l}");
    }
}

/// Renders an `--orbit frames` sequence of `scene` into `dir/{name}_%03d.exr` (+ PNG) with
/// info logs; returns the `--stats` text and the log.
fn orbit_run(
    scene: &Path,
    dir: &Path,
    name: &str,
    frames: u32,
    extra: &[&str],
) -> (String, String) {
    let out = dir.join(format!("{name}_%03d.exr"));
    let stats = dir.join(format!("{name}.jsonl"));
    let n = frames.to_string();
    let mut args = vec!["--orbit", &n, "--stats", stats.to_str().unwrap()];
    args.extend_from_slice(extra);
    let o = render_scene(scene, &out, &args, &[("RUST_LOG", "info")]);
    assert!(
        o.status.success(),
        "{name}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    (
        std::fs::read_to_string(&stats).unwrap(),
        strip_ansi(&String::from_utf8_lossy(&o.stderr)),
    )
}

#[test]
fn an_orbit_renders_every_frame_on_one_set_of_workers_like_in_process() {
    let dir = tempfile::tempdir().unwrap();
    let scene = survey().join("scene.toml");
    let go = |name: &str, extra: &[&str]| orbit_run(&scene, dir.path(), name, 3, extra);
    let (in_stats, _) = go("in", &["--in-process"]);
    let (dist_stats, log) = go("dist", &["--workers", "2"]);
    let frame = |name: &str, i: u32| {
        let p = dir.path().join(format!("{name}_{i:03}.png"));
        assert!(p.exists(), "{} missing", p.display());
        read_exr(&dir.path().join(format!("{name}_{i:03}.exr")))
    };
    for i in 0..3 {
        let d = max_diff(&frame("in", i), &frame("dist", i));
        assert!(d <= 1e-5, "frame {i}: distributed differs by {d}");
    }
    assert!(
        max_diff(&frame("in", 0), &frame("in", 1)) > 0.01,
        "the camera moves between frames"
    );
    let count = |s: &str, kind: &str| s.matches(&format!("\"kind\":\"{kind}\"")).count();
    assert_eq!(count(&in_stats, "frame"), 3, "{in_stats}");
    assert_eq!(count(&dist_stats, "frame"), 3, "{dist_stats}");
    assert_eq!(count(&dist_stats, "worker"), 6, "{dist_stats}");
    assert!(dist_stats.contains("\"frame_count\":3"), "{dist_stats}");
    // One set of workers serves the whole sequence.
    assert_eq!(log.matches("worker joined").count(), 2, "{log}");
    // Both summaries report the same quantities under the same names, filled in.
    let summary = |s: &str| -> serde_json::Value {
        let l = s
            .lines()
            .find(|l| l.contains("\"kind\":\"summary\""))
            .unwrap();
        serde_json::from_str(l).unwrap()
    };
    let (a, b) = (summary(&in_stats), summary(&dist_stats));
    let keys = |v: &serde_json::Value| {
        let mut k: Vec<String> = v.as_object().unwrap().keys().cloned().collect();
        k.sort();
        k
    };
    assert_eq!(keys(&a), keys(&b));
    for v in [&a, &b] {
        let f = |k: &str| v[k].as_f64().unwrap_or_else(|| panic!("{k} in {v}"));
        assert!(f("pages_read") > 0.0 && f("bytes_read") > 0.0, "{v}");
        assert!((0.0..=1.0).contains(&f("cache_hit_rate")), "{v}");
        // The last frame is the final round's cast, a part of all casting.
        assert!(f("last_frame_seconds") > 0.0, "{v}");
        assert!(f("last_frame_seconds") < f("cast_seconds"), "{v}");
        assert!(f("composite_seconds") >= 0.0, "{v}");
    }
    // Each frame line carries its render per round, loads and compositing, under the same
    // names in both modes.
    let frames = |s: &str| -> Vec<serde_json::Value> {
        s.lines()
            .filter(|l| l.contains("\"kind\":\"frame\""))
            .map(|l| serde_json::from_str(l).unwrap())
            .collect()
    };
    let (fa, fb) = (frames(&in_stats), frames(&dist_stats));
    assert_eq!(keys(&fa[0]), keys(&fb[0]));
    let workers: Vec<serde_json::Value> = dist_stats
        .lines()
        .filter(|l| l.contains("\"kind\":\"worker\""))
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    for (mode, lines) in [("in-process", &fa), ("distributed", &fb)] {
        for (i, v) in lines.iter().enumerate() {
            let f = |k: &str| v[k].as_f64().unwrap_or_else(|| panic!("{k} in {v}"));
            let rounds: Vec<f64> = v["round_cast_seconds"]
                .as_array()
                .unwrap()
                .iter()
                .map(|r| r.as_f64().unwrap())
                .collect();
            let loads = v["round_load_seconds"].as_array().unwrap();
            assert_eq!(
                rounds.len() as u64,
                v["rounds"].as_u64().unwrap(),
                "{mode}: {v}"
            );
            assert_eq!(loads.len(), rounds.len(), "{mode}: {v}");
            assert!(rounds.iter().all(|&r| r > 0.0), "{mode}: {v}");
            assert!(
                f("last_round_seconds") > 0.0 && f("cast_seconds") > 0.0,
                "{mode}: {v}"
            );
            if mode == "in-process" {
                // One engine: its rounds add up to its casting.
                let sum: f64 = rounds.iter().sum();
                assert!((sum - f("cast_seconds")).abs() < 1e-9, "{mode}: {v}");
                assert_eq!(f("composite_seconds"), 0.0);
            } else {
                // The slowest worker's cast in each round; casting summed over them.
                let mine: Vec<&serde_json::Value> =
                    workers.iter().filter(|w| w["frame"] == i as u64).collect();
                assert_eq!(mine.len(), 2);
                for (k, &r) in rounds.iter().enumerate() {
                    let slowest = mine
                        .iter()
                        .filter_map(|w| w["round_cast_s"][k].as_f64())
                        .fold(0.0, f64::max);
                    assert_eq!(r, slowest, "round {k}: {v}");
                }
                let cast: f64 = mine.iter().map(|w| w["cast_s"].as_f64().unwrap()).sum();
                assert!((cast - f("cast_seconds")).abs() < 1e-9, "{v}");
                assert!(f("composite_seconds") > 0.0, "{v}");
            }
        }
    }

    // A sequence needs numbered outputs: refused before anything is rendered or written.
    let plain = dir.path().join("plain.png");
    let o = run(
        &[
            "render",
            scene.to_str().unwrap(),
            "-o",
            plain.to_str().unwrap(),
            "--orbit",
            "2",
            "--in-process",
        ],
        &[],
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("frame-number pattern"), "{err}");
    assert!(!plain.exists());
}

/// The lines of a `--stats` file of one `kind`, parsed.
fn lines_of_kind(stats: &str, kind: &str) -> Vec<serde_json::Value> {
    let tag = format!("\"kind\":\"{kind}\"");
    stats
        .lines()
        .filter(|l| l.contains(&tag))
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

#[test]
fn a_sequence_that_re_splits_the_tree_still_equals_in_process_frame_by_frame() {
    let dir = tempfile::tempdir().unwrap();
    // 5×5×2 bricks: fine enough that measured costs move the split planes off the
    // estimate's brick boundaries.
    let scene = synth_survey(&dir.path().join("big"), ["256", "256", "64"], "3");
    let go = |name: &str, extra: &[&str]| orbit_run(&scene, dir.path(), name, 4, extra);
    go("in", &["--in-process"]);
    // Threshold 1: any measured imbalance re-splits; 2 leaves per worker, full steps.
    // `set` (a `cluster.` key) None: the defaults.
    let resplit = |name: &str, setting: Option<&str>| {
        let set = setting.map(|m| format!("cluster.{m}"));
        let mut args = vec![
            "--workers",
            "3",
            "--set",
            "cluster.rebalance_threshold=1.0",
            "--set",
            "cluster.rebalance_damping=1.0",
            "--set",
            "cluster.leaves_per_worker=2",
        ];
        if let Some(set) = &set {
            args.extend(["--set", set.as_str()]);
        }
        let r = go(name, &args);
        for i in 0..4 {
            let a = read_exr(&dir.path().join(format!("in_{i:03}.exr")));
            let b = read_exr(&dir.path().join(format!("{name}_{i:03}.exr")));
            let d = max_diff(&a, &b);
            assert!(
                d <= 1e-5,
                "frame {i} after re-splits ({setting:?}) differs by {d}"
            );
        }
        r
    };
    // One factor per leaf.
    let (stats, log) = resplit("re", Some("rebalance_model=leaves"));
    let rebalances = lines_of_kind(&stats, "rebalance");
    assert!(!rebalances.is_empty(), "no re-split: {stats}");
    for r in &rebalances {
        let measured = r["measured_imbalance"].as_f64().unwrap();
        assert!(measured > 1.0, "{r}");
        // What the new split is expected to leave of the measured imbalance: less of it.
        let expected = r["expected_imbalance"].as_f64().unwrap();
        assert!(expected >= 1.0 - 1e-9 && expected < measured, "{r}");
        assert_ne!(r["old_leaves"], r["new_leaves"], "{r}");
        assert_eq!(r["model"], "leaves", "{r}");
        // The CPU backend times its tiles' threads: leaves are measured by CPU time.
        assert_eq!(r["clock"], "cpu", "{r}");
    }
    assert!(log.contains("new regions after a re-split"), "{log}");
    for w in lines_of_kind(&stats, "worker") {
        // Two leaves each, both with a CPU time and a wall time.
        let cpu = w["leaf_cpu_s"].as_array().unwrap();
        let wall = w["leaf_cast_s"].as_array().unwrap();
        assert_eq!((cpu.len(), wall.len()), (2, 2), "{w}");
        assert!(cpu.iter().all(|c| c.as_f64().unwrap() > 0.0), "{w}");
    }
    // Measured by wall time, as asked.
    let (stats, _) = resplit("wall", Some("rebalance_clock=wall"));
    let rebalances = lines_of_kind(&stats, "rebalance");
    assert!(!rebalances.is_empty(), "no re-split: {stats}");
    for r in &rebalances {
        assert_eq!(r["clock"], "wall", "{r}");
    }
    // By the pages the rays entered (the default): re-splits too, from the workers' page
    // records.
    let (stats, _) = resplit("pg", None);
    let rebalances = lines_of_kind(&stats, "rebalance");
    assert!(!rebalances.is_empty(), "no re-split: {stats}");
    for r in &rebalances {
        assert_eq!(r["model"], "pages", "{r}");
        assert_eq!(r["clock"], "cpu", "{r}");
        assert!(r["page_records"].as_u64().unwrap() > 0, "{r}");
    }
    let workers = lines_of_kind(&stats, "worker");
    assert!(!workers.is_empty(), "{stats}");
    for w in &workers {
        // Each worker's rays, and its process's CPU time: the render's within the frame's.
        assert!(w["rays"].as_u64().unwrap() > 0, "{w}");
        let (render, all) = (
            w["render_cpu_s"].as_f64().unwrap(),
            w["cpu_s"].as_f64().unwrap(),
        );
        assert!(render > 0.0 && all >= render, "{w}");
    }
    // Off: no re-split.
    let (stats, _) = go(
        "off",
        &["--workers", "3", "--set", "cluster.rebalance_threshold=0"],
    );
    assert!(!stats.contains("\"kind\":\"rebalance\""), "{stats}");
}

/// A hand-driven worker for hostile-peer tests: connects to a waiting coordinator with the
/// run's secret, claims this host for shared memory, and returns its endpoint, control
/// stream and set-up.
/// A client with a fresh certificate, connected to the coordinator at `addr` and presenting
/// it (as a worker does).
async fn dial(
    addr: std::net::SocketAddr,
    pinned: strata_common::wire::Fingerprint,
) -> (strata_net::Identity, quinn::Endpoint, quinn::Connection) {
    let id = strata_net::Identity::generate().unwrap();
    let net = strata_net::NetConfig::default();
    let ep = strata_net::transport::endpoint("127.0.0.1:0".parse().unwrap(), &id, &net).unwrap();
    let conn = strata_net::transport::connect_as(
        &ep,
        addr,
        pinned,
        Some(&id),
        &net,
        Duration::from_secs(10),
    )
    .await
    .unwrap();
    (id, ep, conn)
}

async fn fake_worker(
    w: &Waiting,
) -> (
    quinn::Endpoint,
    quinn::Connection,
    quinn::SendStream,
    quinn::RecvStream,
    strata_common::wire::Setup,
) {
    use strata_common::wire::{self, CoordMsg, Limits, WorkerMsg};
    let pinned = strata_net::tls::parse_fingerprint(&w.fingerprint).unwrap();
    let addr: std::net::SocketAddr = format!("127.0.0.1:{}", w.port).parse().unwrap();
    let (id, ep, conn) = dial(addr, pinned).await;
    strata_net::transport::trust(&conn);
    let (mut send, mut recv) = conn.open_bi().await.unwrap();
    let hello = WorkerMsg::Hello {
        secret: strata_common::wire::Secret(b"correct-horse-battery-staple-42".to_vec()),
        name: "fake".into(),
        pid: std::process::id(),
        fingerprint: id.fingerprint,
        host: strata_net::shm::host_id(),
    };
    strata_net::write_frame(&mut send, &wire::encode_meta(&hello), &[])
        .await
        .unwrap();
    let limits = Limits {
        max_meta: wire::MAX_META,
        max_bulk: 0,
    };
    let f = strata_net::read_frame(&mut recv, &limits).await.unwrap();
    let CoordMsg::Setup(setup) = wire::decode_meta::<CoordMsg>(&f.meta).unwrap() else {
        panic!("expected the set-up")
    };
    (ep, conn, send, recv, *setup)
}

/// A small runtime for the hand-driven peers of a test.
fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap()
}

/// Accepts the connection of a peer that dials the fake worker, and reads its hello.
async fn accept_dialling_peer(ep: &quinn::Endpoint) -> quinn::Connection {
    let incoming = tokio::time::timeout(Duration::from_secs(20), ep.accept())
        .await
        .unwrap()
        .unwrap();
    let peer = incoming.await.unwrap();
    strata_net::transport::trust(&peer);
    let _hello = peer.accept_uni().await.unwrap();
    // The dialler meshes only once welcomed.
    strata_net::send_uni(
        &peer,
        &strata_common::wire::encode_meta(&strata_common::wire::PeerMsg::Welcome),
        &[],
    )
    .await
    .unwrap();
    peer
}

/// The fake worker announces a (real) gather segment when asked to, then says it is
/// ready; the segment must be kept alive by the caller.
async fn fake_ready(
    send: &mut quinn::SendStream,
    shm_gather: bool,
) -> Option<strata_net::shm::ShmWriter> {
    use strata_common::wire::{self, WorkerMsg};
    let gather = shm_gather.then(|| strata_net::shm::ShmWriter::create().unwrap());
    if let Some(g) = &gather {
        let id = g.id();
        let msg = WorkerMsg::ShmSegment {
            name: id.name,
            pid: id.pid,
            fd: id.fd,
        };
        strata_net::write_frame(send, &wire::encode_meta(&msg), &[])
            .await
            .unwrap();
    }
    strata_net::write_frame(send, &wire::encode_meta(&WorkerMsg::Ready), &[])
        .await
        .unwrap();
    gather
}

/// Waits for the coordinator to exit and returns its status and log.
fn finish(mut w: Waiting) -> (std::process::ExitStatus, String) {
    let status = w.child.wait().unwrap();
    std::thread::sleep(Duration::from_millis(300));
    let log = std::fs::read_to_string(w.dir.path().join("coordinator.log")).unwrap();
    (status, log)
}

/// A fake worker's side after its set-up: announces a real gather segment, says it is
/// ready and reads its first frame request.
async fn segment_ready_and_frame(
    send: &mut quinn::SendStream,
    recv: &mut quinn::RecvStream,
) -> (
    strata_net::shm::ShmWriter,
    strata_common::wire::FrameRequest,
) {
    use strata_common::wire::{self, CoordMsg, Limits};
    let seg = fake_ready(send, true).await.unwrap();
    let limits = Limits {
        max_meta: wire::MAX_META,
        max_bulk: 0,
    };
    let f = strata_net::read_frame(recv, &limits).await.unwrap();
    let CoordMsg::Frame(req) = wire::decode_meta::<CoordMsg>(&f.meta).unwrap() else {
        panic!("expected a frame")
    };
    (seg, req)
}

/// The fake worker sends `msg` and stays connected while the coordinator reacts.
async fn say_then_linger(send: &mut quinn::SendStream, msg: &strata_common::wire::WorkerMsg) {
    strata_net::write_frame(send, &strata_common::wire::encode_meta(msg), &[])
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_secs(2)).await;
}

/// The coordinator failed: its last log line (the error) and its whole log.
fn failed(w: Waiting) -> (String, String) {
    let (status, log) = finish(w);
    assert!(!status.success(), "{log}");
    (log.lines().last().unwrap_or_default().to_string(), log)
}

#[test]
fn a_bad_shared_memory_segment_of_a_worker_is_refused_naming_it() {
    use strata_common::wire::{ShmRef, WorkerMsg};
    if strata_net::shm::host_id().is_none() {
        eprintln!("skipped: this host has no /dev/shm");
        return;
    }
    let rt = runtime();

    // 1. A segment that does not exist, announced at set-up.
    let w = start_waiting_coordinator(1, &[]);
    rt.block_on(async {
        let (_ep, _conn, mut send, _recv, setup) = fake_worker(&w).await;
        assert!(
            setup.shm_gather,
            "a worker on this host gathers through shared memory"
        );
        let msg = WorkerMsg::ShmSegment {
            name: format!("strata-shm-{}", "0f".repeat(16)),
            pid: std::process::id(),
            fd: 1 << 20,
        };
        say_then_linger(&mut send, &msg).await;
    });
    let (last, log) = failed(w);
    assert!(
        last.contains("the shared-memory segment of worker 0 (fake"),
        "{log}"
    );

    // 2. A real segment, but the final piece's size runs past its end.
    let w = start_waiting_coordinator(1, &[]);
    rt.block_on(async {
        let (_ep, _conn, mut send, mut recv, _setup) = fake_worker(&w).await;
        let (mut seg, req) = segment_ready_and_frame(&mut send, &mut recv).await;
        let at = seg.write(req.frame, u32::MAX, 0, &[0u8; 16]).unwrap();
        let msg = WorkerMsg::FrameDone {
            frame: req.frame,
            stats: Default::default(),
            shm: Some(ShmRef {
                offset: at.offset + seg.size() - 16,
                len: 100,
            }),
            lz4: false,
            canvas: None,
        };
        say_then_linger(&mut send, &msg).await;
    });
    let (last, log) = failed(w);
    assert!(
        last.contains("the final piece of worker 0 (fake")
            && last.contains("runs past the segment's end"),
        "{log}"
    );

    // 3. A worker on this host is given the frame's canvas, and claims pixels past the
    // frame's end in it.
    let (last, log) = frame_done_fails(&rt, |req| {
        assert!(
            req.canvas.is_some(),
            "a worker on this host gets the canvas"
        );
        let n = req.width * req.height;
        WorkerMsg::FrameDone {
            frame: req.frame,
            stats: Default::default(),
            shm: None,
            lz4: false,
            canvas: Some(strata_common::composite::Span {
                start: 0,
                end: n + 5,
            }),
        }
    });
    assert!(last.contains("into the canvas of a"), "{log}");

    // 4. Frame stats that claim another rank (a wall frame's tile check indexed the
    // workers by it).
    let (last, log) = frame_done_fails(&rt, |req| WorkerMsg::FrameDone {
        frame: req.frame,
        stats: strata_common::wire::WorkerFrameStats {
            rank: 999,
            ..Default::default()
        },
        shm: None,
        lz4: false,
        canvas: None,
    });
    assert!(last.contains("frame stats of rank 999"), "{log}");

    // 5. A compressed final piece in a run that does not compress.
    let (last, log) = frame_done_fails(&rt, |req| {
        assert!(!req.composite.lz4);
        WorkerMsg::FrameDone {
            frame: req.frame,
            stats: Default::default(),
            shm: None,
            lz4: true,
            canvas: None,
        }
    });
    assert!(last.contains("without composite.lz4"), "{log}");

    // 6. Frame stats with a time that is not a number (it reached the summary as NaN).
    let (last, log) = frame_done_fails(&rt, |req| WorkerMsg::FrameDone {
        frame: req.frame,
        stats: strata_common::wire::WorkerFrameStats {
            cast_s: f64::NAN,
            ..Default::default()
        },
        shm: None,
        lz4: false,
        canvas: Some(strata_common::composite::Span { start: 0, end: 0 }),
    });
    assert!(last.contains("cast_s = NaN"), "{log}");
}

/// A fake worker on this host, alone in a waiting coordinator's run, answers its first
/// frame with `done(request)`; the run must fail naming it. Returns the coordinator's last
/// log line and its whole log.
fn frame_done_fails(
    rt: &tokio::runtime::Runtime,
    done: impl FnOnce(&strata_common::wire::FrameRequest) -> strata_common::wire::WorkerMsg,
) -> (String, String) {
    let w = start_waiting_coordinator(1, &[]);
    rt.block_on(async {
        let (_ep, _conn, mut send, mut recv, _setup) = fake_worker(&w).await;
        let (_seg, req) = segment_ready_and_frame(&mut send, &mut recv).await;
        say_then_linger(&mut send, &done(&req)).await;
    });
    let (last, log) = failed(w);
    assert!(last.contains("worker 0 (fake"), "{log}");
    (last, log)
}

#[test]
fn a_bad_segment_from_a_peer_fails_the_frame_naming_that_peer() {
    use strata_common::wire::PeerMsg;
    if strata_net::shm::host_id().is_none() {
        eprintln!("skipped: this host has no /dev/shm");
        return;
    }
    // Rank 0 dials us; answer its hello with a segment that does not exist.
    let msg = PeerMsg::ShmSegment {
        name: format!("strata-shm-{}", "ab".repeat(16)),
        pid: std::process::id(),
        fd: 1 << 20,
    };
    a_peer_message_fails_the_frame(msg, &[], "shared-memory segment of worker 1 (fake");
}

#[test]
fn a_compressed_piece_in_a_run_without_lz4_fails_the_frame_naming_its_sender() {
    use strata_common::wire::PeerMsg;
    let msg = PeerMsg::Piece {
        frame: 0,
        round: 0,
        from: 1,
        lz4: true,
    };
    a_peer_message_fails_the_frame(msg, &[0u8; 64], "a compressed piece from worker 1 (fake");
}

/// A fake rank 1, dialled by a real rank 0, sends `msg` (with `bulk`) on the peer
/// connection; the frame must fail on worker 0 with an error containing `needle`.
fn a_peer_message_fails_the_frame(msg: strata_common::wire::PeerMsg, bulk: &[u8], needle: &str) {
    use strata_common::wire;
    // Fail instead of re-rendering without the peer, to see the error itself.
    let w = start_waiting_coordinator(2, &["--set", "cluster.on_worker_loss=\"fail\""]);
    // A real worker joins first (rank 0) and will dial the fake (rank 1).
    let mut real = spawn_real_worker(w.port, &w.fingerprint, Stdio::null());
    wait_for_log(&w.dir.path().join("coordinator.log"), "worker joined");
    let rt = runtime();
    rt.block_on(async {
        let (ep, _conn, mut send, _recv, setup) = fake_worker(&w).await;
        assert_eq!(setup.rank, 1);
        let peer = accept_dialling_peer(&ep).await;
        strata_net::send_uni(&peer, &wire::encode_meta(&msg), bulk)
            .await
            .unwrap();
        let _gather = fake_ready(&mut send, setup.shm_gather).await;
        tokio::time::sleep(Duration::from_secs(3)).await;
    });
    let (status, log) = finish(w);
    let _ = real.kill();
    let _ = real.wait();
    assert!(!status.success());
    let last = log.lines().last().unwrap_or_default();
    assert!(
        last.contains("failed on worker 0") && last.contains(needle),
        "{log}"
    );
}

/// Waits (at most 30 s) until `log` contains `what`.
fn wait_for_log(log: &Path, what: &str) {
    let t = Instant::now();
    while !std::fs::read_to_string(log)
        .unwrap_or_default()
        .contains(what)
    {
        assert!(t.elapsed() < Duration::from_secs(30), "never saw {what:?}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// A real worker process joining the waiting coordinator at `port`.
fn spawn_real_worker(port: u16, fingerprint: &str, stderr: Stdio) -> Child {
    Command::new(BIN)
        .args(["worker", "--connect"])
        .arg(format!("127.0.0.1:{port}"))
        .args(["--fingerprint", fingerprint, "--connect-timeout-s", "20"])
        .env("STRATA_SECRET", "correct-horse-battery-staple-42")
        .stdout(Stdio::null())
        .stderr(stderr)
        .spawn()
        .unwrap()
}

/// Starts a real worker for `w` once the coordinator has logged `after` (so ranks are
/// assigned in a known order), its log going to `err`.
fn spawn_worker_after(
    w: &Waiting,
    after: &'static str,
    err: PathBuf,
) -> std::thread::JoinHandle<Child> {
    let log = w.dir.path().join("coordinator.log");
    let (port, fp) = (w.port, w.fingerprint.clone());
    std::thread::spawn(move || {
        wait_for_log(&log, after);
        spawn_real_worker(port, &fp, Stdio::from(std::fs::File::create(err).unwrap()))
    })
}

#[test]
fn a_peer_claiming_a_rank_with_another_certificate_is_refused() {
    use strata_common::wire::{self, PeerMsg};
    let mut w = start_waiting_coordinator(2, &[]);
    let err = w.dir.path().join("real.err");
    // The fake joins first (rank 0, which dials rank 1); the real worker is rank 1.
    let spawner = spawn_worker_after(&w, "name=fake", err.clone());
    let rt = runtime();
    rt.block_on(async {
        let (_ep, _conn, _send, _recv, setup) = fake_worker(&w).await;
        assert_eq!(setup.rank, 0);
        // Dial rank 1 with the right run token and rank, but a certificate other than the
        // one this rank registered with the coordinator.
        let other = strata_net::Identity::generate().unwrap();
        let net = strata_net::NetConfig::default();
        let ep =
            strata_net::transport::endpoint("127.0.0.1:0".parse().unwrap(), &other, &net).unwrap();
        let peer = &setup.peers[1];
        let c = strata_net::transport::connect_as(
            &ep,
            peer.addr.parse().unwrap(),
            peer.fingerprint,
            Some(&other),
            &net,
            Duration::from_secs(10),
        )
        .await
        .unwrap();
        let hello = PeerMsg::Hello {
            token: setup.run_token,
            rank: 0,
        };
        strata_net::send_uni(&c, &wire::encode_meta(&hello), &[])
            .await
            .unwrap();
        let closed = tokio::time::timeout(Duration::from_secs(15), c.closed())
            .await
            .expect("the impostor's connection stays open");
        assert!(closed.to_string().contains("refused"), "{closed}");
    });
    let _ = w.child.kill();
    let _ = w.child.wait();
    let mut real = spawner.join().unwrap();
    let _ = real.kill();
    let _ = real.wait();
    let log = strip_ansi(&std::fs::read_to_string(&err).unwrap());
    assert!(
        log.contains("claims rank 0 but presented certificate"),
        "{log}"
    );
}

#[test]
fn a_half_sent_stream_loses_its_sender_and_the_frame_is_rendered_without_it() {
    use strata_common::wire::{self, PeerMsg};
    let w = start_waiting_coordinator(2, &["--set", "cluster.frame_timeout_s=5"]);
    // Outlives the coordinator's folder, which `finish` removes.
    let logs = tempfile::tempdir().unwrap();
    let err = logs.path().join("real.err");
    // The real worker is rank 0; the fake (rank 1) accepts its connection and then sends
    // a piece stream that never finishes.
    let mut real = spawn_real_worker(
        w.port,
        &w.fingerprint,
        Stdio::from(std::fs::File::create(&err).unwrap()),
    );
    wait_for_log(&w.dir.path().join("coordinator.log"), "worker joined");
    let rt = runtime();
    let wait = rt.block_on(async {
        let (ep, _conn, mut send, _recv, setup) = fake_worker(&w).await;
        assert_eq!(setup.rank, 1);
        let peer = accept_dialling_peer(&ep).await;
        let _gather = fake_ready(&mut send, setup.shm_gather).await;
        // A piece whose header promises 1000 bytes, of which 10 are sent.
        let mut s = peer.open_uni().await.unwrap();
        let meta = wire::encode_meta(&PeerMsg::Piece {
            frame: 0,
            round: 0,
            from: 1,
            lz4: false,
        });
        s.write_all(&wire::encode_header(meta.len() as u32, 1000))
            .await
            .unwrap();
        s.write_all(&meta).await.unwrap();
        s.write_all(&[0u8; 10]).await.unwrap();
        // Stay connected (silent) until the coordinator is done.
        tokio::task::spawn_blocking(move || finish(w))
            .await
            .unwrap()
    });
    let (status, coordinator_log) = wait;
    let _ = real.kill();
    let _ = real.wait();
    assert!(status.success(), "{coordinator_log}");
    assert!(
        coordinator_log.contains("re-rendering the frame without worker 1 (fake"),
        "{coordinator_log}"
    );
    let log = strip_ansi(&std::fs::read_to_string(&err).unwrap());
    assert!(log.contains("left a stream half-sent"), "{log}");
}

#[test]
fn no_worker_outlives_a_sigkilled_coordinator() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("coordinator.log");
    let out = dir.path().join("f_%03d.png");
    let mut c = Command::new(BIN)
        .args([
            "render",
            survey().join("scene.toml").to_str().unwrap(),
            "-o",
        ])
        .arg(&out)
        .args(["--size", SIZE, "--workers", "3", "--orbit", "100000"])
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    wait_for_log(&log, "all workers ready");
    let text = strip_ansi(&std::fs::read_to_string(&log).unwrap());
    let pids: Vec<String> = text
        .lines()
        .filter(|l| l.contains("worker joined"))
        .map(|l| {
            l.split("pid=")
                .nth(1)
                .and_then(|r| r.split_whitespace().next())
                .unwrap()
                .to_string()
        })
        .collect();
    assert_eq!(pids.len(), 3, "{text}");
    // SIGKILL: no chance to shut anything down.
    c.kill().unwrap();
    c.wait().unwrap();
    let t = Instant::now();
    loop {
        let alive: Vec<&String> = pids
            .iter()
            .filter(|pid| {
                let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
                // Gone, or a zombie awaiting a reaper.
                !(stat.is_empty() || stat.split_whitespace().nth(2) == Some("Z"))
            })
            .collect();
        if alive.is_empty() {
            break;
        }
        // Well under the 10 s idle timeout: they die with it, not by noticing later.
        assert!(
            t.elapsed() < Duration::from_secs(5),
            "workers {alive:?} outlived the coordinator"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn slices_render_the_same_distributed_as_in_process() {
    // The survey's scene with an inline, a crossline and a time slice (written next to
    // it: store paths are relative to the scene file).
    let text = std::fs::read_to_string(survey().join("scene.toml")).unwrap();
    let with = text.replacen(
        "[[volume]]\n",
        "[[volume]]\nslices = [{ axis = \"inline\", index = 17.5 }, { axis = \"crossline\", index = 9 }, { axis = \"time\", index = 15, opacity = 0.7 }]\n",
        1,
    );
    assert_ne!(with, text);
    let scene = survey().join("scene-slices.toml");
    std::fs::write(&scene, with).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let go = |name: &str, extra: &[&str]| {
        let out = dir.path().join(format!("{name}.exr"));
        let o = render_scene(&scene, &out, extra, &[]);
        assert!(
            o.status.success(),
            "{name}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        read_exr(&out)
    };
    let single = go("in", &["--in-process"]);
    let split = go("dist", &["--workers", "3"]);
    let d = max_diff(&single, &split);
    assert!(d <= 1e-5, "distributed slices differ by {d}");
    assert!(
        max_diff(&single, reference()) > 0.01,
        "the slices change the image"
    );
}

/// Per worker and frame, `(frame, occlusion_shift)` of a `--stats` file.
fn worker_shifts(stats: &str) -> Vec<(u64, [i64; 2])> {
    stats
        .lines()
        .filter(|l| l.contains("\"kind\":\"worker\""))
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            let s = &v["occlusion_shift"];
            let c = |i: usize| {
                s[i].as_i64()
                    .unwrap_or_else(|| panic!("occlusion_shift in {v}"))
            };
            (v["frame"].as_u64().unwrap(), [c(0), c(1)])
        })
        .collect()
}

/// Per-frame `(samples, occluded_blocks, fixup_blocks)` of a `--stats` file.
fn frame_counts(stats: &str) -> Vec<(u64, u64, u64)> {
    stats
        .lines()
        .filter(|l| l.contains("\"kind\":\"frame\""))
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            let n = |k: &str| v[k].as_u64().unwrap_or_else(|| panic!("{k} in {v}"));
            (n("samples"), n("occluded_blocks"), n("fixup_blocks"))
        })
        .collect()
}

#[test]
fn cross_worker_occlusion_casts_less_and_stays_within_the_termination_bound() {
    let dir = tempfile::tempdir().unwrap();
    // Opaque horizons and a dense volume: the workers behind have much that is hidden.
    let scene = synth_survey(&dir.path().join("survey"), ["80", "64", "48"], "5");
    // Four frames of a 40-frame orbit (9° apart): each frame predicts from the last, and
    // the camera moves enough that some predictions fail and are re-cast.
    let go = |name: &str, extra: &[&str]| {
        let out = dir.path().join(format!("{name}_%03d.exr"));
        let stats = dir.path().join(format!("{name}.jsonl"));
        let mut args = vec![
            "--orbit",
            "40",
            "--frames",
            "0..4",
            "--stats",
            stats.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let o = render_scene(&scene, &out, &args, &[]);
        assert!(
            o.status.success(),
            "{name}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let frames: Vec<Vec<[f32; 4]>> = (0..4)
            .map(|i| read_exr(&dir.path().join(format!("{name}_{i:03}.exr"))))
            .collect();
        (
            frames,
            frame_counts(&std::fs::read_to_string(stats).unwrap()),
        )
    };
    // No re-split from measured (noisy) times: every run splits the scene alike, so sample
    // counts compare.
    let ert = [
        "--set",
        "render.early_termination=0.99",
        "--set",
        "cluster.rebalance_threshold=0",
    ];
    let (inp, _) = go("in", &[&ert[..], &["--in-process"]].concat());
    // The last frame's map moved with each worker's region (the default; the re-casts are
    // exercised), and widened by the camera's motion below.
    let (on, on_n) = go(
        "on",
        &[
            &ert[..],
            &["--workers", "3", "--set", "cluster.occlusion_motion=false"],
        ]
        .concat(),
    );
    let (off, off_n) = go(
        "off",
        &[
            &ert[..],
            &["--workers", "3", "--set", "cluster.occlusion=false"],
        ]
        .concat(),
    );
    for i in 0..4 {
        // Early termination at t may move a pixel by 1 − t, in-process as distributed.
        let d = max_diff(&on[i], &inp[i]);
        assert!(
            d <= 0.01 + 1e-5,
            "frame {i}: occlusion moved a pixel by {d}"
        );
        let d = max_diff(&off[i], &inp[i]);
        assert!(
            d <= 0.01 + 1e-5,
            "frame {i}: without occlusion a pixel moved by {d}"
        );
    }
    assert!(off_n.iter().all(|f| f.1 == 0 && f.2 == 0), "{off_n:?}");
    // The coordinator's time on the maps, per frame: some with occlusion, none without.
    let map_s = |name: &str| -> Vec<f64> {
        std::fs::read_to_string(dir.path().join(format!("{name}.jsonl")))
            .unwrap()
            .lines()
            .filter(|l| l.contains("\"kind\":\"frame\""))
            .map(|l| {
                let v: serde_json::Value = serde_json::from_str(l).unwrap();
                v["occlusion_map_seconds"].as_f64().unwrap()
            })
            .collect()
    };
    let (on_s, off_s) = (map_s("on"), map_s("off"));
    assert!(on_s.len() == 4 && on_s.iter().all(|&s| s > 0.0), "{on_s:?}");
    assert!(
        off_s.len() == 4 && off_s.iter().all(|&s| s == 0.0),
        "{off_s:?}"
    );
    // The first frame predicts from a first pass at 1/4 of the resolution; without it
    // there is nothing to predict from.
    // (Whether it pays depends on the frame: at this 96×64 size its 1/16 of the rays and
    // the re-casts of its coarse guesses cost about what it saves; BENCHMARKS measures
    // the demo.)
    assert!(on_n[0].1 > 0, "the first pass hid nothing: {on_n:?}");
    let (nopre, nopre_n) = go(
        "nopre",
        &[
            &ert[..],
            &["--workers", "3", "--set", "cluster.occlusion_prepass=false"],
        ]
        .concat(),
    );
    assert_eq!(nopre_n[0].1, 0, "{nopre_n:?}");
    for i in 0..4 {
        let d = max_diff(&nopre[i], &inp[i]);
        assert!(d <= 0.01 + 1e-5, "frame {i} without the first pass: {d}");
    }
    for i in 1..4 {
        assert!(on_n[i].1 > 0, "frame {i}: no block left out: {on_n:?}");
        assert!(
            on_n[i].0 < off_n[i].0,
            "frame {i}: occlusion cast {} samples, without {}",
            on_n[i].0,
            off_n[i].0
        );
    }
    assert!(
        on_n.iter().map(|f| f.2).sum::<u64>() > 0,
        "the moving camera made no prediction fail, so no re-cast was exercised: {on_n:?}"
    );
    // Widened by the camera's motion: fewer blocks turn out stale, and the bound holds.
    let (moving, moving_n) = go(
        "moving",
        &[
            &ert[..],
            &["--workers", "3", "--set", "cluster.occlusion_motion=true"],
        ]
        .concat(),
    );
    for i in 0..4 {
        let d = max_diff(&moving[i], &inp[i]);
        assert!(d <= 0.01 + 1e-5, "frame {i}, widened by the motion: {d}");
    }
    assert!(moving_n[1..].iter().all(|f| f.1 > 0), "{moving_n:?}");
    // The map as it is moves with each worker's region on screen (the camera turns 9° a
    // frame); widened, it does not move.
    let shifts = |name: &str| {
        worker_shifts(&std::fs::read_to_string(dir.path().join(format!("{name}.jsonl"))).unwrap())
    };
    let on_shifts = shifts("on");
    assert!(
        on_shifts.iter().all(|&(f, s)| f > 0 || s == [0, 0])
            && on_shifts.iter().any(|&(f, s)| f > 0 && s != [0, 0]),
        "{on_shifts:?}"
    );
    let moving_shifts = shifts("moving");
    assert!(
        moving_shifts.iter().all(|&(_, s)| s == [0, 0]),
        "{moving_shifts:?}"
    );
    let recast = |n: &[(u64, u64, u64)]| n[1..].iter().map(|f| f.2).sum::<u64>();
    assert!(
        recast(&moving_n) < recast(&on_n),
        "widening by the motion re-cast {} blocks, the map moved with the region {}: {moving_n:?} {on_n:?}",
        recast(&moving_n),
        recast(&on_n)
    );
    // Several leaves per worker: each leaf's own rays decide what is re-cast (a leaf that
    // stopped short can hide behind the next one's opacity in their composite).
    let (two, two_n) = go(
        "two",
        &[
            &ert[..],
            &["--workers", "3", "--set", "cluster.leaves_per_worker=2"],
        ]
        .concat(),
    );
    for i in 0..4 {
        let d = max_diff(&two[i], &inp[i]);
        assert!(d <= 0.01 + 1e-5, "frame {i}, 2 leaves per worker: {d}");
    }
    assert!(two_n[1..].iter().all(|f| f.1 > 0), "{two_n:?}");
    // At t = 1 only exactly opaque content hides anything, and the image is the same.
    let (in1, _) = go("in1", &["--in-process"]);
    let (on1, on1_n) = go(
        "on1",
        &["--workers", "3", "--set", "cluster.rebalance_threshold=0"],
    );
    for i in 0..4 {
        let d = max_diff(&on1[i], &in1[i]);
        assert!(
            d <= 1e-5,
            "frame {i} at t = 1: occlusion moved a pixel by {d}"
        );
    }
    assert!(on1_n[1..].iter().all(|f| f.1 > 0), "{on1_n:?}");
    // GPU workers take the same limits (lavapipe in CI; skipped without an adapter unless
    // one is required).
    if strata_worker::gpu::list_adapters().is_empty() {
        assert_ne!(
            std::env::var("STRATA_REQUIRE_GPU_ADAPTER").as_deref(),
            Ok("1"),
            "STRATA_REQUIRE_GPU_ADAPTER=1 but wgpu finds no adapter"
        );
        eprintln!("NOTICE: GPU workers under occlusion skipped, no wgpu adapter");
        return;
    }
    let (gpu, gpu_n) = go(
        "gpu",
        &[&ert[..], &["--workers", "3", "--set", "render.backend=gpu"]].concat(),
    );
    for i in 0..4 {
        let d = max_diff(&gpu[i], &inp[i]);
        assert!(
            d <= 0.01 + 1e-4,
            "frame {i}: GPU workers under occlusion differ by {d}"
        );
    }
    let (_, gpu_off_n) = go(
        "gpu-off",
        &[
            &ert[..],
            &[
                "--workers",
                "3",
                "--set",
                "render.backend=gpu",
                "--set",
                "cluster.occlusion=false",
            ],
        ]
        .concat(),
    );
    for i in 1..4 {
        assert!(
            gpu_n[i].1 > 0,
            "frame {i}: no block left out on the GPU: {gpu_n:?}"
        );
        assert!(
            gpu_n[i].0 < gpu_off_n[i].0,
            "frame {i}: {gpu_n:?} against {gpu_off_n:?}"
        );
    }
}

/// A 3×2 wall of 24×20 tiles with 6×4-pixel mullions: every tile equals the crop of one
/// render of the whole frustum (84×44, mullions included), in-process and distributed; each
/// tile is written by the rank that drives it, which receives pieces of its own tiles only,
/// and a rank that drives nothing receives nothing.
#[test]
fn a_wall_renders_each_tile_on_its_driver_like_the_crop_of_one_frustum() {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("wall");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let scene = survey().join("scene.toml");
    let go = |name: &str, extra: &[&str]| -> PathBuf {
        let png = dir.join(format!("{name}.png"));
        let exr = dir.join(format!("{name}.exr"));
        let stats = dir.join(format!("{name}.jsonl"));
        let mut args = vec![
            "render",
            scene.to_str().unwrap(),
            "-o",
            png.to_str().unwrap(),
            "--exr",
            exr.to_str().unwrap(),
            "--stats",
            stats.to_str().unwrap(),
            "--set",
            "render.early_termination=1.0",
        ];
        args.extend_from_slice(extra);
        let o = run(&args, &[]);
        assert!(
            o.status.success(),
            "{name}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        png
    };
    let wall = [
        "--set",
        "wall.tiles=[3,2]",
        "--set",
        "wall.tile_size=[24,20]",
        "--set",
        "wall.mullion=[6,4]",
    ];
    go("plane", &["--in-process", "--size", "84x44"]);
    let plane = read_exr_sized(&dir.join("plane.exr"), 84);
    let mut local = wall.to_vec();
    local.push("--in-process");
    go("local", &local);
    let mut dist = wall.to_vec();
    dist.extend(["--workers", "3", "--set", "wall.ranks=[0,0,0,2,2,2]"]);
    go("dist", &dist);
    let mut worst = 0.0f32;
    for t in 0..6u32 {
        let (c, r) = (t % 3, t / 3);
        let crop: Vec<[f32; 4]> = (0..20)
            .flat_map(|y| {
                let row = (r * 24 + y) as usize * 84 + (c * 30) as usize;
                plane[row..row + 24].to_vec()
            })
            .collect();
        let local = read_exr_sized(&dir.join(format!("local_c{c}r{r}.exr")), 24);
        let dist = read_exr_sized(&dir.join(format!("dist_c{c}r{r}.exr")), 24);
        worst = worst.max(max_diff(&local, &crop));
        assert!(
            max_diff(&local, &crop) <= 1e-5,
            "tile ({c}, {r}) in-process vs the frustum's crop"
        );
        assert!(
            max_diff(&dist, &local) <= 1e-5,
            "tile ({c}, {r}) distributed vs in-process"
        );
        assert!(dir.join(format!("dist_c{c}r{r}.png")).is_file());
    }
    let alpha: f32 = plane.iter().map(|p| p[3]).sum();
    assert!(
        alpha > 50.0,
        "the survey must be visible on the wall (alpha {alpha})"
    );
    eprintln!("wall tiles vs the frustum's crop: max difference {worst:e}");
    // The preview mosaic: the frustum's size, mullions drawn in.
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(dir.join("dist.png")).unwrap(),
    ));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!((info.width, info.height), (84, 44));
    for (x, y) in [(24, 0), (29, 43), (0, 20), (83, 23), (55, 21)] {
        let i = (y * 84 + x) * 3;
        assert_eq!(
            buf[i..i + 3],
            strata_worker::image_out::MULLION_RGB,
            "({x}, {y})"
        );
    }
    // Drivers: rank 0 tiles 0-2, rank 2 tiles 3-5, rank 1 none.
    let stats = std::fs::read_to_string(dir.join("dist.jsonl")).unwrap();
    let workers: Vec<serde_json::Value> = stats
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .filter(|v| v["kind"] == "worker")
        .collect();
    assert_eq!(workers.len(), 3);
    let tile_bytes = 24 * 20 * 16u64;
    // The drivers write the tiles: what reaches the coordinator is each worker's frame
    // stats and an empty final piece, less than one tile's pixels in all.
    let summary: serde_json::Value = stats
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .find(|v| v["kind"] == "summary")
        .unwrap();
    let gathered = summary["gather_bytes"].as_u64().unwrap();
    assert!(gathered < tile_bytes / 2, "{summary}");
    assert_eq!(summary["canvas_gather"], 0, "{summary}");
    for w in &workers {
        let rank = w["rank"].as_u64().unwrap();
        let written = w["tiles_written"].as_u64().unwrap();
        let received = w["bytes_received"].as_u64().unwrap();
        match rank {
            0 | 2 => {
                assert_eq!(written, 3, "{w}");
                // At most the two other ranks' pieces of its three tiles (plus headers).
                assert!(received <= 2 * 3 * tile_bytes + 2 * 64, "{w}");
            }
            _ => {
                assert_eq!(written, 0, "{w}");
                assert_eq!(received, 0, "{w}");
            }
        }
    }
    // A rank's tiles must be consecutive: an error naming the rule, no panic.
    let png = dir.join("bad.png");
    let o = run(
        &[
            "render",
            scene.to_str().unwrap(),
            "-o",
            png.to_str().unwrap(),
            "--workers",
            "2",
            "--set",
            "wall.tiles=[3,1]",
            "--set",
            "wall.tile_size=[8,8]",
            "--set",
            "wall.ranks=[0,1,0]",
        ],
        &[],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("consecutive"), "{err}");
    assert!(!png.exists());
}
