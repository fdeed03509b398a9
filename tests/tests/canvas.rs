//! The gather into the coordinator's shared canvas (`strata_net::canvas`): workers on the
//! coordinator's host write their final spans in place. The image must equal the one
//! assembled from pieces sent over QUIC, bit for bit, with and without interlacing, and a
//! frame a caller still holds must not be written by the next one. (Also: a frame cannot
//! change the run's `composite.lz4`.)

use std::path::PathBuf;
use strata_common::composite::{Algorithm, WireFormat};
use strata_common::image::Rgba;
use strata_common::scene::Scene;
use strata_common::scene::Transport;
use strata_common::wire::{CompositeChoice, FrameSource};
use strata_coordinator::cluster::{Cluster, ClusterOptions, FrameImage};

const W: u32 = 97;
const H: u32 = 61;
const WORKERS: usize = 3;

fn scene(dir: &std::path::Path) -> Scene {
    let survey = dir.join("survey");
    strata_coordinator::synth::synth(
        &survey,
        [16, 16, 16],
        1,
        false,
        &indicatif::ProgressBar::hidden(),
    )
    .unwrap();
    let path = survey.join("scene.toml");
    let mut s = Scene::parse(&path, &std::fs::read_to_string(&path).unwrap()).unwrap();
    s.render.width = W;
    s.render.height = H;
    s.cluster.frame_timeout_s = 120.0;
    s.cluster.connect_timeout_s = 60.0;
    s
}

/// Options for `workers` test workers of one thread over `transport`, and a runtime.
fn cluster_of(
    s: &Scene,
    workers: usize,
    transport: Transport,
) -> (ClusterOptions, tokio::runtime::Runtime) {
    let mut opts = ClusterOptions::from_scene(s, Some(workers)).unwrap();
    opts.worker_exe = Some(PathBuf::from(env!("CARGO_BIN_EXE_strata-test-worker")));
    opts.worker_threads = 1;
    opts.transport = transport;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    (opts, rt)
}

/// Frames of synthetic images (no rendering) on one cluster, for each `(coverage,
/// interlace, seed)`; `hold` keeps every image alive until the end.
#[allow(clippy::type_complexity)]
fn frames(
    s: &Scene,
    transport: Transport,
    shots: &[(f32, bool, u64)],
) -> (Vec<Vec<Rgba>>, Vec<(usize, usize)>, Vec<FrameImage>) {
    let (opts, rt) = cluster_of(s, WORKERS, transport);
    let camera = s.camera.clone().unwrap();
    rt.block_on(async {
        let mut c = Cluster::start(s, opts).await.unwrap();
        let (mut copies, mut in_canvas, mut held) = (Vec::new(), Vec::new(), Vec::new());
        for &(coverage, interlace, seed) in shots {
            let choice = CompositeChoice {
                algorithm: Algorithm::RadixK,
                k: vec![WORKERS as u32],
                interlace,
                format: WireFormat::F32,
                lz4: false,
            };
            let r = c
                .frame(
                    &camera,
                    W,
                    H,
                    &choice,
                    FrameSource::Synthetic { coverage, seed },
                )
                .await
                .unwrap();
            assert!(r.lost.is_empty());
            copies.push(r.image.to_vec());
            in_canvas.push((r.canvas_gather, r.canvas_blended));
            held.push(r.image);
        }
        c.shutdown().await;
        (copies, in_canvas, held)
    })
}

fn opaque_pixels(img: &[Rgba]) -> usize {
    img.iter().filter(|p| p[3] > 0.0).count()
}

#[test]
fn the_canvas_equals_the_assembled_image_and_a_held_frame_stays_as_it_was() {
    if strata_net::shm::host_id().is_none() {
        eprintln!("skipped: this host has no shared memory between processes");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let s = scene(dir.path());
    // Dense and sparse, interlaced and not, and a repeat of the first shot after others.
    let shots = [
        (1.0, false, 1),
        (0.3, true, 2),
        (0.3, false, 3),
        (1.0, true, 4),
        (1.0, false, 1),
    ];
    let (canvas, in_canvas, held) = frames(&s, Transport::Shm, &shots);
    let (quic, over_quic, _) = frames(&s, Transport::Quic, &shots);
    // Every worker wrote in place, and blended its last round straight into the canvas,
    // interlaced or not.
    let want: Vec<(usize, usize)> = vec![(WORKERS, WORKERS); shots.len()];
    assert_eq!(in_canvas, want);
    assert_eq!(
        over_quic,
        vec![(0, 0); shots.len()],
        "QUIC gathers send pieces"
    );
    for (i, (a, b)) in canvas.iter().zip(&quic).enumerate() {
        assert!(opaque_pixels(a) > 100, "shot {i}: blank");
        assert!(
            a == b,
            "shot {i}: the canvas differs from the assembled image"
        );
    }
    // Every frame was held while the later ones ran: none was written again.
    for (i, (h, c)) in held.iter().zip(&canvas).enumerate() {
        assert!(h[..] == c[..], "frame {i} changed after it was returned");
        assert!(
            matches!(h, FrameImage::Canvas(_)),
            "frame {i} not in a canvas"
        );
    }
    assert!(
        canvas[0] != canvas[3],
        "the shots must differ for this test to mean anything"
    );
    assert!(canvas[0] == canvas[4]);
}

/// `composite.lz4` is a run setting: the workers' peer readers accept compressed pieces only
/// in a run set up with it, so a frame that asks for the other setting is refused before
/// anything is sent, and the run goes on.
#[test]
fn a_frame_cannot_change_the_runs_lz4_setting() {
    let dir = tempfile::tempdir().unwrap();
    let s = scene(dir.path());
    assert!(!s.composite.lz4);
    let (opts, rt) = cluster_of(&s, 2, Transport::Quic);
    let camera = s.camera.clone().unwrap();
    rt.block_on(async {
        let mut c = Cluster::start(&s, opts).await.unwrap();
        let mut choice = CompositeChoice {
            algorithm: Algorithm::BinarySwap,
            k: vec![2],
            interlace: false,
            format: WireFormat::F32,
            lz4: true,
        };
        let source = FrameSource::Synthetic {
            coverage: 1.0,
            seed: 1,
        };
        let err = c
            .frame(&camera, W, H, &choice, source.clone())
            .await
            .err()
            .expect("refused");
        let msg = format!("{err:#}");
        assert!(
            msg.contains("composite.lz4 is false for this run's workers"),
            "{msg}"
        );
        choice.lz4 = false;
        let r = c.frame(&camera, W, H, &choice, source).await.unwrap();
        assert!(r.lost.is_empty());
        assert!(opaque_pixels(&r.image) > 100);
        c.shutdown().await;
    });
}
