//! Replays the fuzzing corpus (`fuzz/corpus/<target>/`: the seeds, what AFL++ found
//! interesting, minimised, and any input that once crashed a target) and freshly written
//! seeds through every fuzz target (`strata_tests::fuzz`). Every input must be accepted or
//! refused with an error: a panic names the file.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;
use strata_tests::fuzz::{seeds, TARGETS};

fn run(target: &str, f: fn(&[u8]), what: &str, data: &[u8]) {
    if catch_unwind(AssertUnwindSafe(|| f(data))).is_err() {
        panic!("fuzz target {target} panicked on {what}");
    }
}

#[test]
fn every_corpus_input_is_accepted_or_refused_without_a_panic() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/corpus");
    let mut total = 0;
    for (target, f) in TARGETS {
        let dir = root.join(target);
        let mut files: Vec<_> = std::fs::read_dir(&dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| e.unwrap().path())
            .collect();
        files.sort();
        // The corpus is what AFL++ kept (minimised to one input per distinct edge set), not
        // an empty folder: the smallest formats (a 24-byte frame header) keep a handful.
        assert!(
            files.len() >= 3,
            "{}: only {} inputs",
            dir.display(),
            files.len()
        );
        for p in &files {
            let data = std::fs::read(p).unwrap();
            run(target, f, &p.display().to_string(), &data);
        }
        total += files.len();
    }
    assert!(total >= 500, "only {total} corpus inputs");
    eprintln!("{total} corpus inputs replayed");
}

#[test]
fn inputs_that_once_crashed_a_target_no_longer_panic() {
    // fuzz/regressions/<target>/: what the fuzzer found, kept after the fix (that each is
    // also refused with an error is checked per format: the store's below).
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/regressions");
    let mut n = 0;
    for (target, f) in TARGETS {
        let Ok(dir) = std::fs::read_dir(root.join(target)) else {
            continue;
        };
        for e in dir {
            let p = e.unwrap().path();
            run(
                target,
                f,
                &p.display().to_string(),
                &std::fs::read(&p).unwrap(),
            );
            n += 1;
        }
    }
    assert!(n > 0, "no regression inputs in {}", root.display());
}

#[test]
fn a_crafted_length_inside_a_store_header_is_refused_before_allocation() {
    // AFL++ found (store_sealed): a CRC-valid header whose string length prefix claims
    // exabytes made the reader abort on allocation. Now it is an error naming the header.
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/regressions/store_sealed");
    let dir = tempfile::TempDir::new().unwrap();
    // Every input the fuzzer kept for this target: each must be refused, not only not panic.
    let names: Vec<String> = std::fs::read_dir(&root)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(names.len() >= 8, "{names:?}");
    for name in &names {
        let name = name.as_str();
        let mut b = std::fs::read(root.join(name)).unwrap();
        strata_tests::fuzz::seal_store(&mut b);
        let p = dir.path().join(name);
        std::fs::write(&p, &b).unwrap();
        let e = strata_common::store::PageStore::open(&p)
            .err()
            .unwrap_or_else(|| panic!("{name} opened"))
            .to_string();
        assert!(e.contains(name) && e.contains("header"), "{name}: {e}");
    }
}

#[test]
fn the_seeds_are_accepted_by_their_readers() {
    // The seeds are valid inputs: the readers must accept them (so the corpus starts from
    // deep inside each format, not at its first check).
    use strata_common::composite::SparsePiece;
    let all = seeds();
    for (target, _) in TARGETS {
        assert!(
            all.iter().any(|(t, _, _)| *t == target),
            "no seed for {target}"
        );
    }
    for (target, name, data) in &all {
        let f = strata_tests::fuzz::target(target).unwrap();
        run(target, f, name, data);
        match *target {
            "sparse_piece" => {
                let ok = if data[0] & 1 == 0 {
                    SparsePiece::parse(&data[1..], 4096).is_ok()
                } else {
                    SparsePiece::parse_lz4(&data[1..], 4096).is_ok()
                };
                assert!(ok, "seed {name} does not parse");
            }
            "scene_toml" => {
                let text = std::str::from_utf8(data).unwrap();
                strata_common::scene::Scene::parse(Path::new(name), text)
                    .unwrap_or_else(|e| panic!("seed {name}: {e}"));
            }
            "wire_header" => {
                let h = data.first_chunk().unwrap();
                strata_common::wire::decode_header(
                    h,
                    &strata_common::wire::Limits::for_pixels(1 << 22),
                )
                .unwrap_or_else(|e| panic!("seed {name}: {e}"));
            }
            "segy" | "store" | "store_sealed" => {
                let dir = tempfile::TempDir::new().unwrap();
                let p = dir.path().join(name);
                std::fs::write(&p, data).unwrap();
                if *target == "segy" {
                    // A pre-stack file opens only as one offset or a stack.
                    let opts = strata_coordinator::segy::SegyOptions {
                        stack: name == "prestack",
                        ..Default::default()
                    };
                    strata_coordinator::segy::open(&p, &opts)
                        .unwrap_or_else(|e| panic!("seed {name}: {e:#}"));
                } else {
                    strata_common::store::PageStore::open(&p)
                        .unwrap_or_else(|e| panic!("seed {name}: {e}"));
                }
            }
            "horizon_text" => {
                use strata_coordinator::horizon_text::{
                    parse_horizon, HorizonFormat, HorizonParseOptions,
                };
                let dir = tempfile::TempDir::new().unwrap();
                let p = dir.path().join(name);
                std::fs::write(&p, &data[1..]).unwrap();
                // The target's format choice, from the first byte.
                let format = match data.first().map(|b| b % 4) {
                    Some(1) => HorizonFormat::Grid,
                    Some(2) => HorizonFormat::IlXlZ,
                    Some(3) => HorizonFormat::XyIlXlZ,
                    _ => HorizonFormat::Auto,
                };
                let opts = HorizonParseOptions {
                    format,
                    null_value: Some(-999.25),
                    ..HorizonParseOptions::default()
                };
                parse_horizon(&p, &opts).unwrap_or_else(|e| panic!("seed {name}: {e:#}"));
            }
            "wire_message" => {
                use strata_common::wire::{
                    decode_meta, CoordMsg, FrameRequest, PeerMsg, Setup, WorkerMsg,
                };
                let (kind, rest) = data.split_first().unwrap();
                let ok = match kind % 5 {
                    0 => decode_meta::<CoordMsg>(rest).is_ok(),
                    1 => decode_meta::<WorkerMsg>(rest).is_ok(),
                    2 => decode_meta::<PeerMsg>(rest).is_ok(),
                    3 => decode_meta::<Setup>(rest).is_ok(),
                    _ => decode_meta::<FrameRequest>(rest).is_ok(),
                };
                assert!(ok, "seed {name} does not decode");
            }
            other => panic!("no acceptance check for the seeds of {other}"),
        }
    }
}
