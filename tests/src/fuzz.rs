//! Fuzz targets: one function per untrusted input, fed arbitrary bytes. Each must return
//! (accepting or refusing the input with an error), never panic, hang or allocate without
//! bound. The coverage-guided fuzzer (`fuzz/`, cargo-afl) calls these, and
//! `tests/tests/fuzz_corpus.rs` replays the checked-in corpus through them in CI.
//!
//! The file-based readers (SEG-Y, horizon text, page store) get the bytes as a file in a
//! per-process scratch folder, as a user's file would reach them.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// The targets by name, as the fuzzer and the corpus folders name them.
#[allow(clippy::type_complexity)]
pub const TARGETS: [(&str, fn(&[u8])); 8] = [
    ("segy", segy),
    ("horizon_text", horizon_text),
    ("store", store),
    ("store_sealed", store_sealed),
    ("wire_header", wire_header),
    ("wire_message", wire_message),
    ("sparse_piece", sparse_piece),
    ("scene_toml", scene_toml),
];

/// The target called `name`.
pub fn target(name: &str) -> Option<fn(&[u8])> {
    TARGETS.iter().find(|(n, _)| *n == name).map(|(_, f)| *f)
}

/// A scratch file of this process (in `/dev/shm` where there is one: the fuzzer writes it
/// once per execution) holding `data`; removed when dropped, so no run leaves files behind.
fn scratch(name: &str, data: &[u8]) -> Scratch {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    let dir = DIR.get_or_init(|| {
        if Path::new("/dev/shm").is_dir() {
            PathBuf::from("/dev/shm")
        } else {
            std::env::temp_dir()
        }
    });
    let p = dir.join(format!("strata-fuzz-{}-{name}", std::process::id()));
    std::fs::write(&p, data).expect("scratch file");
    Scratch(p)
}

/// A scratch file, removed on drop.
struct Scratch(PathBuf);

impl std::ops::Deref for Scratch {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for Scratch {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// A SEG-Y file: headers, trace scan and grid fit; if it opens, its first and last traces
/// are read, and the first node's column through the grid (a stack, with `--stack`).
pub fn segy(data: &[u8]) {
    use strata_coordinator::segy::{open, SegyOptions, VerticalDomain, VerticalUnit};
    use strata_coordinator::source::GridSource;
    let p = scratch("in.sgy", data);
    // The options are user input too: the last byte (sample data, which the textual
    // header's fixed first byte is not) picks the byte positions of inline and crossline,
    // one offset of a pre-stack file (100, as in the seed) or its stack, and the vertical
    // axis.
    let opts = match data.last().map(|b| b % 8) {
        Some(1) => SegyOptions {
            inline_byte: 9,
            xline_byte: 21,
            ..SegyOptions::default()
        },
        Some(2) => SegyOptions {
            inline_byte: 5,
            xline_byte: 237,
            ..SegyOptions::default()
        },
        Some(3) => SegyOptions {
            stack: true,
            ..SegyOptions::default()
        },
        Some(4) => SegyOptions {
            offset: Some(100),
            ..SegyOptions::default()
        },
        Some(5) => SegyOptions {
            vertical: Some(VerticalDomain::Depth),
            vertical_unit: Some(VerticalUnit::Ft),
            ..SegyOptions::default()
        },
        Some(6) => SegyOptions {
            vertical_unit: Some(VerticalUnit::S),
            z_step: Some(0.5),
            ..SegyOptions::default()
        },
        _ => SegyOptions::default(),
    };
    if let Ok(v) = open(&p, &opts) {
        let n = v.info().samples_per_trace as usize;
        if n <= 1 << 16 {
            let mut out = vec![0.0f32; n];
            let traces = v.info().trace_count;
            for t in [0, traces.saturating_sub(1)] {
                let _ = v.read_trace(t, &mut out);
            }
            let _ = v.read_box([0, 0, 0], [1, 1, n as u64], &mut out);
        }
    }
}

/// Horizon text in each layout (the first byte picks the layout; the text is the rest: with
/// the byte in the file every seed had failed at its first number).
pub fn horizon_text(data: &[u8]) {
    use strata_coordinator::horizon_text::{parse_horizon, HorizonFormat, HorizonParseOptions};
    let p = scratch("in.txt", data.get(1..).unwrap_or_default());
    let format = match data.first().map(|b| b % 4) {
        Some(1) => HorizonFormat::Grid,
        Some(2) => HorizonFormat::IlXlZ,
        Some(3) => HorizonFormat::XyIlXlZ,
        _ => HorizonFormat::Auto,
    };
    let _ = parse_horizon(
        &p,
        &HorizonParseOptions {
            format,
            null_value: Some(-999.25),
            ..HorizonParseOptions::default()
        },
    );
}

/// A page store: preamble, header, index; if it opens, up to eight pages are read and
/// decoded.
pub fn store(data: &[u8]) {
    use strata_common::store::PageStore;
    let p = scratch("in.strata", data);
    if let Ok(s) = PageStore::open(&p) {
        let ids: Vec<_> = s.index().iter().take(8).map(|e| e.id).collect();
        for id in ids {
            let _ = s.read_page(id);
        }
        let _ = s.sample_level(0, [0, 0, 0]);
    }
}

/// A page store whose checksums are made right after mutation (structure-aware): the
/// preamble's, the header's, the index's and every in-range page's CRC-32C are recomputed
/// from the bytes, so mutations reach the header's fields, the index and the page codec
/// instead of stopping at a checksum — a crafted file passes every CRC.
pub fn store_sealed(data: &[u8]) {
    let mut b = data.to_vec();
    seal_store(&mut b);
    store(&b);
}

/// Recomputes a store file's CRCs in place where its offsets lie inside it.
pub fn seal_store(b: &mut [u8]) {
    const PRE: usize = 64;
    const ENTRY: usize = 40;
    if b.len() < PRE {
        return;
    }
    let u64_at = |b: &[u8], at: usize| u64::from_le_bytes(b[at..at + 8].try_into().unwrap());
    let u32_at = |b: &[u8], at: usize| u32::from_le_bytes(b[at..at + 4].try_into().unwrap());
    let range = |off: u64, len: u64, total: usize| -> Option<std::ops::Range<usize>> {
        let end = off.checked_add(len)?;
        (end <= total as u64).then_some(off as usize..end as usize)
    };
    let n = b.len();
    let (ho, hl) = (u64_at(b, 16), u64_at(b, 24));
    let (io, ic) = (u64_at(b, 32), u64_at(b, 40));
    if let Some(r) = ic
        .checked_mul(ENTRY as u64)
        .and_then(|len| range(io, len, n))
    {
        // Each page's checksum over its stored bytes, then the index's over the entries.
        for e in r.clone().step_by(ENTRY) {
            let (off, len) = (u64_at(b, e + 8), u32_at(b, e + 16) as u64);
            if let Some(p) = range(off, len, n) {
                let c = crc32c::crc32c(&b[p]);
                b[e + 20..e + 24].copy_from_slice(&c.to_le_bytes());
            }
        }
        let c = crc32c::crc32c(&b[r]);
        b[52..56].copy_from_slice(&c.to_le_bytes());
    }
    if let Some(r) = range(ho, hl, n) {
        let c = crc32c::crc32c(&b[r]);
        b[48..52].copy_from_slice(&c.to_le_bytes());
    }
    let c = crc32c::crc32c(&b[..60]);
    b[60..64].copy_from_slice(&c.to_le_bytes());
}

/// A frame header of the cluster protocol, under the handshake limits and a frame's.
pub fn wire_header(data: &[u8]) {
    use strata_common::wire::{decode_header, Limits, HEADER_LEN};
    if let Some(h) = data.first_chunk::<HEADER_LEN>() {
        let _ = decode_header(h, &Limits::HANDSHAKE);
        let _ = decode_header(h, &Limits::for_pixels(1 << 22));
    }
}

/// A meta message of the cluster protocol: the first byte picks the type, the rest is the
/// message; a frame request that decodes is checked as the worker checks it.
pub fn wire_message(data: &[u8]) {
    use strata_common::wire::{decode_meta, CoordMsg, FrameRequest, PeerMsg, Setup, WorkerMsg};
    let Some((&kind, rest)) = data.split_first() else {
        return;
    };
    match kind % 5 {
        0 => {
            let _ = decode_meta::<CoordMsg>(rest);
        }
        1 => {
            let _ = decode_meta::<WorkerMsg>(rest);
        }
        2 => {
            let _ = decode_meta::<PeerMsg>(rest);
        }
        3 => {
            let _ = decode_meta::<Setup>(rest);
        }
        _ => {
            if let Ok(r) = decode_meta::<FrameRequest>(rest) {
                if let Some(w) = &r.wall {
                    let _ = w.check(r.width, r.height, &r.order);
                }
            }
        }
    }
}

/// A compositing piece, plain and LZ4, with an image of up to 4096 pixels; a piece that
/// parses is blended into a span of that size.
pub fn sparse_piece(data: &[u8]) {
    use strata_common::composite::SparsePiece;
    const MAX: u32 = 4096;
    let Some((&kind, rest)) = data.split_first() else {
        return;
    };
    let piece = if kind & 1 == 0 {
        SparsePiece::parse(rest, MAX)
    } else {
        SparsePiece::parse_lz4(rest, MAX)
    };
    if let Ok(p) = piece {
        let mut dst = vec![[0.0f32; 4]; MAX as usize];
        let _ = p.blend_over(&mut dst, 0);
        let _ = p.blend_under(&mut dst, 0);
        let _ = p.decode_into(&mut dst, 0);
    }
}

/// A scene file (TOML), with its checks.
pub fn scene_toml(data: &[u8]) {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = strata_common::scene::Scene::parse(Path::new("fuzz.toml"), text);
    }
}

/// Valid inputs for each target, written with Strata's own writers (the corpus seeds):
/// `(target, name, bytes)`.
pub fn seeds() -> Vec<(&'static str, String, Vec<u8>)> {
    let mut out = Vec::new();
    let dir = std::env::temp_dir().join(format!("strata-fuzz-seeds-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("seed folder");
    // SEG-Y: a 3×4×6 cube in each sample format and byte order the writer has.
    {
        use strata_coordinator::segy::{Endian, SegyWriter};
        for (format, endian) in [
            (1, Endian::Big),
            (5, Endian::Little),
            (3, Endian::Big),
            (7, Endian::Big),
            (15, Endian::Little),
        ] {
            let p = dir.join("seed.sgy");
            let mut w = SegyWriter::create(&p, "C 1 fuzz seed", 6, 4000, 0, format, endian)
                .expect("segy writer");
            for i in 0..3 {
                for j in 0..4 {
                    let s: Vec<f32> = (0..6).map(|k| (i * 7 + j * 3 + k) as f32 - 9.0).collect();
                    w.write_trace(100 + i, 200 + 2 * j, 1000.0 + i as f64, 50.0 * j as f64, &s)
                        .expect("trace");
                }
            }
            w.finish().expect("segy finish");
            let name = format!("fmt{format}-{endian:?}").to_lowercase();
            out.push(("segy", name, std::fs::read(&p).expect("segy seed")));
        }
        // A pre-stack file (three offsets per node, one missing) and a depth cube in feet.
        let p = dir.join("seed.sgy");
        let mut w = SegyWriter::create(&p, "C 1 CMP gathers", 6, 4000, 0, 5, Endian::Big)
            .expect("segy writer");
        for i in 0..3 {
            for j in 0..4 {
                for o in [100, 200, 300] {
                    if (i, j, o) == (1, 2, 300) {
                        continue;
                    }
                    w.set_offset(o);
                    let s: Vec<f32> = (0..6).map(|k| (i * 7 + j * 3 + k + o) as f32).collect();
                    w.write_trace(100 + i, 200 + j, 10.0 * i as f64, 10.0 * j as f64, &s)
                        .expect("trace");
                }
            }
        }
        w.finish().expect("segy finish");
        out.push((
            "segy",
            "prestack".into(),
            std::fs::read(&p).expect("segy seed"),
        ));
        let mut w = SegyWriter::create(
            &p,
            "C 1 KIRCHHOFF PSDM\nC 2 DEPTH IN FEET",
            6,
            5000,
            0,
            5,
            Endian::Big,
        )
        .expect("segy writer");
        for i in 0..3 {
            for j in 0..4 {
                let s: Vec<f32> = (0..6).map(|k| (i + j + k) as f32).collect();
                w.write_trace(1 + i, 1 + j, 25.0 * i as f64, 25.0 * j as f64, &s)
                    .expect("trace");
            }
        }
        w.finish().expect("segy finish");
        out.push((
            "segy",
            "depth-ft".into(),
            std::fs::read(&p).expect("segy seed"),
        ));
    }
    // Horizon text: a grid, an inline/crossline/z list and an x/y/inline/crossline/z list.
    for (name, text) in [
        ("grid", "# a grid\n10.5 11.0 -999.25\n12.0 12.5 13.0\n"),
        ("ilxlz", "100 200 1500.5\n100 201 1501.0\n101 200 1502.25\n101 201 -999.25\n"),
        (
            "xyilxlz",
            "605000.0 6075000.0 100 200 1500\n605025.0 6075000.0 100 201 1504\n605000.0 6075025.0 101 200 1508\n",
        ),
    ] {
        let mut b = vec![[0u8, 1, 2, 3][["auto", "grid", "ilxlz", "xyilxlz"]
            .iter()
            .position(|n| *n == name)
            .unwrap_or(0)]];
        b.extend_from_slice(text.as_bytes());
        out.push(("horizon_text", name.into(), b));
    }
    // Page stores: a small volume (two levels) and a horizon.
    {
        use indicatif::ProgressBar;
        use strata_common::sample::SampleType;
        use strata_coordinator::builder::{build_store, BuildOptions};
        use strata_coordinator::source::MemorySource;
        // u8 samples in few, compressible pages: a small file for the fuzzer to mutate.
        let vol = MemorySource {
            dims: [40, 20, 3],
            data: (0..40 * 20 * 3).map(|i| (i / 40 % 5) as f32).collect(),
        };
        let p = dir.join("v.strata");
        let mut o = BuildOptions::volume("v", SampleType::U8);
        o.page_size = 32;
        o.compression = strata_common::store::Compression::Lz4;
        build_store(&vol, &p, &o, &ProgressBar::hidden()).expect("volume seed");
        out.push((
            "store",
            "volume".into(),
            std::fs::read(&p).expect("store seed"),
        ));
        let hor = MemorySource {
            dims: [40, 7, 1],
            data: (0..280)
                .map(|i| if i % 9 == 0 { f32::NAN } else { i as f32 })
                .collect(),
        };
        let p = dir.join("h.strata");
        let mut o = BuildOptions::horizon("h");
        o.page_size = 32;
        o.compression = strata_common::store::Compression::Lz4;
        build_store(&hor, &p, &o, &ProgressBar::hidden()).expect("horizon seed");
        out.push((
            "store",
            "horizon".into(),
            std::fs::read(&p).expect("store seed"),
        ));
        // The sealed target starts from the same valid files.
        let sealed: Vec<_> = out
            .iter()
            .filter(|(t, _, _)| *t == "store")
            .map(|(_, n, b)| ("store_sealed", n.clone(), b.clone()))
            .collect();
        out.extend(sealed);
    }
    // The cluster protocol: frame headers and one message of each kind.
    {
        use strata_common::composite::Algorithm;
        use strata_common::composite::WireFormat;
        use strata_common::wire::*;
        out.push(("wire_header", "meta".into(), encode_header(40, 0).to_vec()));
        out.push((
            "wire_header",
            "bulk".into(),
            encode_header(24, 1 << 20).to_vec(),
        ));
        let tagged = |k: u8, meta: Vec<u8>| {
            let mut b = vec![k];
            b.extend(meta);
            b
        };
        out.push((
            "wire_message",
            "coord-peer-lost".into(),
            tagged(0, encode_meta(&CoordMsg::PeerLost { rank: 2 })),
        ));
        out.push((
            "wire_message",
            "worker-frame-done".into(),
            tagged(
                1,
                encode_meta(&WorkerMsg::FrameDone {
                    frame: 3,
                    stats: WorkerFrameStats {
                        outcome: "converged".into(),
                        effects: "volume".into(),
                        ..Default::default()
                    },
                    shm: None,
                    lz4: false,
                    canvas: None,
                }),
            ),
        ));
        out.push((
            "wire_message",
            "peer-piece".into(),
            tagged(
                2,
                encode_meta(&PeerMsg::Piece {
                    frame: 7,
                    round: 1,
                    from: 3,
                    lz4: true,
                }),
            ),
        ));
        let camera = strata_common::scene::Camera {
            eye: [0.0, -10.0, 5.0],
            target: [0.0; 3],
            up: [0.0, 0.0, 1.0],
            fov_deg: 30.0,
        };
        let composite = CompositeChoice {
            algorithm: Algorithm::RadixK,
            k: vec![2, 2],
            interlace: true,
            format: WireFormat::F16,
            lz4: false,
        };
        let request = FrameRequest {
            frame: 1,
            camera,
            width: 64,
            height: 48,
            order: vec![2, 0, 1],
            leaf_order: vec![0],
            composite,
            source: FrameSource::Render,
            leaves: None,
            occlusion_block: 16,
            occlusion_prepass: 4,
            occlusion_motion: 12,
            page_work: true,
            wall: None,
            canvas: Some(strata_common::wire::CanvasRef {
                name: format!("strata-shm-{}", "0f".repeat(16)),
                pid: 4242,
                fd: 9,
            }),
        };
        out.push((
            "wire_message",
            "frame".into(),
            tagged(4, encode_meta(&request)),
        ));
    }
    // Compositing pieces: sparse and dense, f32 and f16, plain and LZ4.
    {
        use strata_common::composite::Span;
        use strata_common::composite::{SparsePiece, WireFormat};
        let px: Vec<[f32; 4]> = (0..300)
            .map(|i| {
                if i % 7 < 3 {
                    [0.0; 4]
                } else {
                    let a = (i % 11) as f32 / 10.0;
                    [a * 0.5, a * 0.25, a * 0.1, a]
                }
            })
            .collect();
        for format in [WireFormat::F32, WireFormat::F16] {
            let p = SparsePiece::encode(
                &px,
                Span {
                    start: 100,
                    end: 400,
                },
                format,
            );
            let mut plain = vec![0u8];
            p.write(&mut plain);
            out.push((
                "sparse_piece",
                format!("{format:?}-plain").to_lowercase(),
                plain,
            ));
            let mut lz = vec![1u8];
            lz.extend(p.write_lz4().unwrap());
            out.push(("sparse_piece", format!("{format:?}-lz4").to_lowercase(), lz));
        }
    }
    // Scene files: the shipped configurations and a minimal one.
    let configs = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs");
    for name in ["demo.toml", "wall.toml"] {
        if let Ok(b) = std::fs::read(configs.join(name)) {
            out.push(("scene_toml", name.replace(".toml", ""), b));
        }
    }
    out.push((
        "scene_toml",
        "minimal".into(),
        b"[[volume]]\nstore = \"a.strata\"\n[render]\nwidth = 64\nheight = 48\n[wall]\ntiles = [2, 1]\n".to_vec(),
    ));
    let _ = std::fs::remove_dir_all(&dir);
    out
}
