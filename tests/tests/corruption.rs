//! Damaged and hostile inputs give clear errors naming the file and position, never a panic.

use indicatif::ProgressBar;
use std::os::unix::fs::FileExt;
use strata_common::sample::SampleType;
use strata_common::store::{PageStore, StoreError};
use strata_coordinator::builder::{build_store, BuildOptions};
use strata_coordinator::inspect::inspect;
use strata_coordinator::source::{MemorySource, RawSource};

fn store(dir: &std::path::Path) -> std::path::PathBuf {
    let dims = [40, 40, 40];
    let data: Vec<f32> = (0..64000).map(|i| ((i * 7919) % 251) as f32).collect();
    let out = dir.join("s.strata");
    let mut o = BuildOptions::volume("c", SampleType::U8);
    o.page_size = 32;
    build_store(
        &MemorySource { dims, data },
        &out,
        &o,
        &ProgressBar::hidden(),
    )
    .unwrap();
    out
}

fn flip(path: &std::path::Path, at: u64) {
    let f = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(path)
        .unwrap();
    let mut b = [0u8];
    f.read_exact_at(&mut b, at).unwrap();
    b[0] ^= 0x40;
    f.write_all_at(&b, at).unwrap();
}

#[test]
fn flipped_byte_in_a_page_is_caught_by_its_checksum() {
    let dir = tempfile::tempdir().unwrap();
    let p = store(dir.path());
    let s = PageStore::open(&p).unwrap();
    let e = *s.index().iter().find(|e| e.has_payload()).unwrap();
    drop(s);
    flip(&p, e.offset + 100);
    let s = PageStore::open(&p).unwrap();
    let err = s.read_page(e.id).unwrap_err();
    assert!(matches!(err, StoreError::Checksum { .. }), "{err}");
    let msg = err.to_string();
    assert!(
        msg.contains("s.strata")
            && msg.contains(&format!("at byte {}", e.offset))
            && msg.contains("checksum"),
        "{msg}"
    );
    let msg = format!(
        "{:#}",
        inspect(&p, true, &ProgressBar::hidden()).unwrap_err()
    );
    assert!(msg.contains("checksum mismatch"), "{msg}");
}

#[test]
fn truncated_store_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let p = store(dir.path());
    let len = std::fs::metadata(&p).unwrap().len();
    for cut in [len - 1, len / 2, 63, 0] {
        let f = std::fs::OpenOptions::new().write(true).open(&p).unwrap();
        f.set_len(cut).unwrap();
        let msg = PageStore::open(&p).unwrap_err().to_string();
        assert!(
            msg.contains("s.strata") && msg.contains("truncated"),
            "cut at {cut}: {msg}"
        );
    }
}

#[test]
fn garbage_in_preamble_header_or_index_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let p = store(dir.path());
    let s = PageStore::open(&p).unwrap();
    let len = s.file_len();
    drop(s);
    let cases = [
        (0u64, "magic"),
        (9, "version"),
        (20, "crc32c"),
        (len - 3, "index"),
        (len - 40 * 9 - 5, "crc32c"),
    ];
    for (at, want) in cases {
        let q = dir.path().join("c.strata");
        std::fs::copy(&p, &q).unwrap();
        flip(&q, at);
        let msg = PageStore::open(&q).unwrap_err().to_string();
        assert!(
            msg.contains("c.strata") && msg.contains("at byte") && msg.contains(want),
            "flip at {at}: {msg}"
        );
    }
    // Not a store at all.
    let q = dir.path().join("text.strata");
    std::fs::write(
        &q,
        "hello, this is not a page store but long enough to have a preamble ........",
    )
    .unwrap();
    assert!(PageStore::open(&q)
        .unwrap_err()
        .to_string()
        .contains("magic"));
}

#[test]
fn raw_with_wrong_dims_names_file_and_sizes() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("v.raw");
    std::fs::write(&p, vec![0u8; 1000]).unwrap();
    let msg = format!(
        "{:#}",
        RawSource::open(&p, [10, 10, 11], SampleType::U8, false)
            .err()
            .unwrap()
    );
    assert!(
        msg.contains("v.raw") && msg.contains("1000 bytes") && msg.contains("expected 1100"),
        "{msg}"
    );
    assert!(RawSource::open(&p, [10, 10, 5], SampleType::U16, false).is_ok());
}

/// A header that decodes and checksums right but holds a NaN or singular index→world
/// transform (every ray and region goes through it) is refused at open, naming the file.
#[test]
fn a_store_whose_transform_is_not_finite_or_invertible_is_refused() {
    for bad in [f64::NAN, 0.0, 1e-100] {
        let dir = tempfile::tempdir().unwrap();
        let p = store(dir.path());
        let mut b = std::fs::read(&p).unwrap();
        let at = |o: usize| u64::from_le_bytes(b[o..o + 8].try_into().unwrap()) as usize;
        let (ho, hl) = (at(16), at(24));
        let cfg = bincode::config::standard();
        let (mut h, _): (strata_common::store::StoreHeader, usize) =
            bincode::serde::decode_from_slice(&b[ho..ho + hl], cfg).unwrap();
        // x's scale: NaN, or 0 (a singular transform).
        h.transform.rows[0][0] = bad;
        let enc = bincode::serde::encode_to_vec(&h, cfg).unwrap();
        assert_eq!(enc.len(), hl, "an f64 keeps its length");
        b[ho..ho + hl].copy_from_slice(&enc);
        strata_tests::fuzz::seal_store(&mut b);
        std::fs::write(&p, &b).unwrap();
        let e = PageStore::open(&p).expect_err("refused").to_string();
        assert!(
            e.contains("s.strata") && e.contains("finite, invertible"),
            "{e}"
        );
    }
}

/// A sealed store (checksums right) whose header claims more valid samples than it has
/// samples, or a survey grid without lines, is refused at open naming the file: `inspect`
/// subtracted and indexed by them (an overflow panic in checked builds). So is a page of
/// one sample per axis.
#[test]
fn a_store_whose_counts_do_not_fit_its_dimensions_is_refused() {
    type Patch = fn(&mut strata_common::store::StoreHeader);
    let patches: [(Patch, &str); 3] = [
        (|h| h.valid_samples = u64::MAX, "valid samples"),
        // A page of one sample (the worker's caster panicked on it).
        (
            |h| {
                h.page_size = 1;
                h.border = 0
            },
            "at least 2 samples",
        ),
        (
            |h| {
                h.survey = Some(strata_common::geo::SurveyGrid {
                    inline0: 0.0,
                    inline_step: 1.0,
                    n_inline: 0,
                    xline0: 0.0,
                    xline_step: 1.0,
                    n_xline: 4,
                    to_world: strata_common::geo::Affine2::IDENTITY,
                })
            },
            "one inline",
        ),
    ];
    for (patch, want) in patches {
        let dir = tempfile::tempdir().unwrap();
        let p = store(dir.path());
        let mut b = std::fs::read(&p).unwrap();
        let at = |b: &[u8], o: usize| u64::from_le_bytes(b[o..o + 8].try_into().unwrap());
        let (ho, hl) = (at(&b, 16) as usize, at(&b, 24) as usize);
        let cfg = bincode::config::standard();
        let (mut h, _): (strata_common::store::StoreHeader, usize) =
            bincode::serde::decode_from_slice(&b[ho..ho + hl], cfg).unwrap();
        patch(&mut h);
        // The new header (its length may differ) goes to the end, the preamble points at it.
        let enc = bincode::serde::encode_to_vec(&h, cfg).unwrap();
        let end = b.len() as u64;
        b.extend_from_slice(&enc);
        b[16..24].copy_from_slice(&end.to_le_bytes());
        b[24..32].copy_from_slice(&(enc.len() as u64).to_le_bytes());
        strata_tests::fuzz::seal_store(&mut b);
        std::fs::write(&p, &b).unwrap();
        let e = PageStore::open(&p).expect_err("refused").to_string();
        assert!(e.contains("s.strata") && e.contains(want), "{e}");
        let e = strata_coordinator::inspect::inspect(&p, false, &indicatif::ProgressBar::hidden())
            .expect_err("refused");
        assert!(format!("{e:#}").contains(want), "{e:#}");
    }
}
