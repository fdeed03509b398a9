//! Real third-party files from `../shared/data/real`: SEG-Y in both byte orders and IBM
//! float, interpreted horizons with holes, CT and MRI volumes as raw (u8, i16 and u16).

use indicatif::ProgressBar;
use strata_common::sample::SampleType;
use strata_common::store::PageStore;
use strata_coordinator::builder::{build_store, BuildOptions};
use strata_coordinator::horizon_text::{parse_horizon, HorizonParseOptions};
use strata_coordinator::inspect::inspect;
use strata_coordinator::segy::{self, SegyOptions};
use strata_coordinator::source::{MemorySource, RawSource};
use strata_tests::{check_borders, check_coarse_levels, level_grid, real_data};

fn ingest_segy(rel: &str, dir: &std::path::Path) -> PageStore {
    let vol = segy::open(&real_data(rel), &SegyOptions::default()).unwrap();
    let out = dir.join(rel.replace('/', "_") + ".strata");
    let mut o = BuildOptions::volume("f3", vol.info().sample_type);
    o.survey = Some(vol.info().survey);
    o.vertical_domain = Some(vol.info().vertical.domain);
    build_store(&vol, &out, &o, &ProgressBar::hidden()).unwrap();
    PageStore::open(&out).unwrap()
}

fn stats(v: &[f32]) -> (f32, f32, f64, f64) {
    let n = v.len() as f64;
    let mean = v.iter().map(|&x| x as f64).sum::<f64>() / n;
    let var = v.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / n;
    let mn = v.iter().cloned().fold(f32::INFINITY, f32::min);
    let mx = v.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
    (mn, mx, mean, var.sqrt())
}

#[test]
fn f3_big_and_little_endian_give_the_same_digest() {
    let dir = tempfile::tempdir().unwrap();
    let be = ingest_segy("seismic/f3_segyio/f3.sgy", dir.path());
    let le = ingest_segy("seismic/f3_segyio/f3-lsb.sgy", dir.path());
    assert_eq!(be.header().dims, [23, 18, 75]);
    assert_eq!(be.header().sample_type, SampleType::I16);
    assert_eq!(be.header().digest, le.header().digest);
    let a = inspect(be.path(), true, &ProgressBar::hidden()).unwrap();
    let b = inspect(le.path(), true, &ProgressBar::hidden()).unwrap();
    assert_eq!(a.digest, b.digest);
    assert!(a
        .text
        .lines()
        .any(|l| l == format!("digest: {:016x}", a.digest)));
    // The README's statistics of the crop: int16, min -10239, max 10827, mean 25.13, std 2160.21.
    let (mn, mx, mean, sd) = stats(&level_grid(&be, 0).unwrap());
    assert_eq!((mn, mx), (-10239.0, 10827.0));
    assert!((mean - 25.13).abs() < 0.01, "{mean}");
    assert!((sd - 2160.21).abs() < 0.01, "{sd}");
    let s = be.header().survey.unwrap();
    assert_eq!(
        (s.inline0, s.n_inline, s.xline0, s.n_xline),
        (111.0, 23, 875.0, 18)
    );
    check_borders(&be).unwrap();
    check_coarse_levels(&be).unwrap();
}

#[test]
fn f3_ibm_float_decodes_to_documented_values() {
    let dir = tempfile::tempdir().unwrap();
    let s = ingest_segy(
        "seismic/f3_opendtect_very_small/F3_very_small.sgy",
        dir.path(),
    );
    assert_eq!(s.header().dims, [11, 11, 463]);
    assert_eq!(s.header().sample_type, SampleType::F32);
    let (mn, mx, mean, sd) = stats(&level_grid(&s, 0).unwrap());
    assert_eq!((mn, mx), (-16032.0, 10745.0));
    assert!((mean - 1.368).abs() < 1e-3, "{mean}");
    assert!((sd - 2404.42).abs() < 0.01, "{sd}");
    assert_eq!(s.header().value_range, [-16032.0, 10745.0]);
}

fn horizon_store(rel: &str, dir: &std::path::Path) -> (PageStore, usize) {
    let g = parse_horizon(&real_data(rel), &HorizonParseOptions::default()).unwrap();
    let holes = g.heights.iter().filter(|v| v.is_nan()).count();
    let out = dir.join("h.strata");
    let _ = std::fs::remove_file(&out);
    let src = MemorySource {
        dims: [g.survey.n_inline, g.survey.n_xline, 1],
        data: g.heights.clone(),
    };
    let mut o = BuildOptions::horizon("h");
    o.survey = Some(g.survey);
    build_store(&src, &out, &o, &ProgressBar::hidden()).unwrap();
    let s = PageStore::open(&out).unwrap();
    let l0 = level_grid(&s, 0).unwrap();
    assert!(
        l0.iter()
            .zip(&g.heights)
            .all(|(a, b)| a == b || (a.is_nan() && b.is_nan())),
        "{rel}: level 0 differs from the file"
    );
    (s, holes)
}

#[test]
fn real_horizons_load_with_their_holes() {
    let dir = tempfile::tempdir().unwrap();
    let (s, holes) = horizon_store("horizons/penobscot_seabed/Penobscot_Seabed.txt", dir.path());
    // The data set's README: 601 × 481 values, 249,572 finite, 39,509 NaN, range
    // 38.39..85.27 (counted from the file, not from this code).
    assert_eq!(s.header().dims, [601, 481, 1]);
    assert_eq!(holes, 39_509);
    assert_eq!(s.header().valid_samples, 249_572);
    assert_eq!(s.header().value_range, [38.39f32 as f64, 85.27f32 as f64]);
    check_borders(&s).unwrap();
    check_coarse_levels(&s).unwrap();

    let (s, holes) = horizon_store("horizons/f3_fs4/F3_Demo_0_FS4.dat", dir.path());
    assert_eq!(s.header().dims, [225, 300, 1]);
    assert_eq!(holes, 0);
    assert_eq!(s.header().valid_samples, 67_500);

    let (s, holes) = horizon_store("horizons/penobscot_hor_b/Hor_B.txt", dir.path());
    assert_eq!(s.header().dims, [250, 200, 1]);
    assert_eq!(holes, 0);
    assert_eq!(s.header().value_range, [8.0, 47.0]);
}

fn ingest_raw(rel: &str, dims: [u64; 3], t: SampleType, dir: &std::path::Path) -> PageStore {
    let src = RawSource::open(&real_data(rel), dims, t, false).unwrap();
    let out = dir.join("v.strata");
    let _ = std::fs::remove_file(&out);
    build_store(
        &src,
        &out,
        &BuildOptions::volume("ct", t),
        &ProgressBar::hidden(),
    )
    .unwrap();
    let s = PageStore::open(&out).unwrap();
    // Level 0 equals the file, sample for sample.
    let bytes = std::fs::read(real_data(rel)).unwrap();
    let mut want = vec![0f32; bytes.len() / t.size()];
    t.decode_le(&bytes, None, &mut want);
    assert_eq!(level_grid(&s, 0).unwrap(), want, "{rel}");
    s
}

#[test]
fn ct_volumes_ingest_as_raw() {
    let dir = tempfile::tempdir().unwrap();
    let s = ingest_raw(
        "volumes/vtk_headsq/headsq_64x64x93_int16le.raw",
        [64, 64, 93],
        SampleType::I16,
        dir.path(),
    );
    assert_eq!(s.header().value_range, [0.0, 3926.0]);
    check_borders(&s).unwrap();
    check_coarse_levels(&s).unwrap();
    let s = ingest_raw(
        "volumes/engine/engine_256x256x128_uint8.raw",
        [256, 256, 128],
        SampleType::U8,
        dir.path(),
    );
    let (_, _, mean, _) = stats(&level_grid(&s, 0).unwrap());
    assert!((mean - 20.694).abs() < 1e-3, "{mean}");
    check_coarse_levels(&s).unwrap();
    let s = ingest_raw(
        "volumes/bonsai/bonsai_256x256x256_uint8.raw",
        [256, 256, 256],
        SampleType::U8,
        dir.path(),
    );
    let (_, _, mean, _) = stats(&level_grid(&s, 0).unwrap());
    assert!((mean - 13.465).abs() < 1e-3, "{mean}");
    // Bonsai's empty background becomes constant pages that store no payload.
    assert!(s.index().iter().any(|e| !e.has_payload()));
}

/// The MRI series (12-bit values in u16, 63 MB): the only real unsigned 16-bit file. Level 0
/// equals the file (in `ingest_raw`); range, mean and non-zero fraction are the README's.
#[test]
fn mri_volume_ingests_as_raw_u16() {
    let dir = tempfile::tempdir().unwrap();
    let s = ingest_raw(
        "volumes/vs_seg_001_t1_mri/vs_seg_001_t1_512x512x120_uint16le.raw",
        [512, 512, 120],
        SampleType::U16,
        dir.path(),
    );
    assert_eq!(s.header().dims, [512, 512, 120]);
    assert_eq!(s.header().value_range, [0.0, 1826.0]);
    let v = level_grid(&s, 0).unwrap();
    let (mn, mx, mean, _) = stats(&v);
    assert_eq!((mn, mx), (0.0, 1826.0));
    assert!((mean - 204.61).abs() < 5e-3, "{mean}");
    let nonzero = v.iter().filter(|&&x| x != 0.0).count() as f64 / v.len() as f64;
    assert!((nonzero - 0.996).abs() < 5e-4, "{nonzero}");
    check_coarse_levels(&s).unwrap();
}

/// Ingest stores mean, RMS and percentiles of the level-0 values; on F3 they match a direct
/// computation (sorting every sample) within the stated resolution, `inspect` prints them,
/// and the seismic display window comes from them. A format-1 store (no statistics) still
/// opens.
#[test]
fn f3_percentile_statistics_match_a_direct_computation() {
    use std::io::{Seek, SeekFrom, Write};
    use strata_common::store::{Preamble, StoreHeader, VerticalDomain, FORMAT_VERSION};
    let dir = tempfile::tempdir().unwrap();
    let be = ingest_segy("seismic/f3_segyio/f3.sgy", dir.path());
    let s = be.header().stats.clone().expect("statistics at ingest");
    let mut v: Vec<f32> = level_grid(&be, 0)
        .unwrap()
        .into_iter()
        .filter(|x| x.is_finite())
        .collect();
    let n = v.len() as f64;
    let mean = v.iter().map(|&x| x as f64).sum::<f64>() / n;
    let rms = (v.iter().map(|&x| (x as f64).powi(2)).sum::<f64>() / n).sqrt();
    assert!((s.mean - mean).abs() <= 1e-9 * rms, "{} vs {mean}", s.mean);
    assert!((s.rms - rms).abs() <= 1e-9 * rms, "{} vs {rms}", s.rms);
    let rank = |sorted: &[f32], p: f64| {
        let r = ((p / 100.0 * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
        sorted[r - 1] as f64
    };
    v.sort_by(f32::total_cmp);
    for &[p, got] in &s.percentiles {
        let want = rank(&v, p);
        assert!(
            (got - want).abs() <= s.resolution * want.abs(),
            "p{p}: {got} vs {want}"
        );
    }
    let mut mags: Vec<f32> = v.iter().map(|x| x.abs()).collect();
    mags.sort_by(f32::total_cmp);
    for &[p, got] in &s.abs_percentiles {
        let want = rank(&mags, p);
        assert!(
            (got - want).abs() <= s.resolution * want.abs(),
            "|p{p}|: {got} vs {want}"
        );
    }
    assert!(s.resolution < 1e-3);
    let text = inspect(be.path(), false, &ProgressBar::hidden())
        .unwrap()
        .text;
    assert!(text.contains("percentiles of |value|: p50 "), "{text}");
    assert!(text.contains(&format!("rms: {:.6}", s.rms)), "{text}");

    // The same store as formats 2 and 1: format 2's header ends before `vertical_domain`,
    // format 1's also before `stats`.
    let path = be.path().to_path_buf();
    drop(be);
    let rewrite = |version: u32, h: &StoreHeader| {
        let bytes = std::fs::read(&path).unwrap();
        let mut pre = Preamble::decode(&path, &bytes[..64]).unwrap();
        let mut hb = bincode::serde::encode_to_vec(h, bincode::config::standard()).unwrap();
        for _ in version..FORMAT_VERSION {
            assert_eq!(hb.pop(), Some(0), "an absent Option is bincode's 0 tag");
        }
        assert!(hb.len() as u64 <= pre.header_len);
        pre.version = version;
        pre.header_len = hb.len() as u64;
        pre.header_crc = crc32c::crc32c(&hb);
        let mut f = std::fs::OpenOptions::new().write(true).open(&path).unwrap();
        f.write_all(&pre.encode()).unwrap();
        f.seek(SeekFrom::Start(pre.header_offset)).unwrap();
        f.write_all(&hb).unwrap();
    };
    let mut h = PageStore::open(&path).unwrap().header().clone();
    assert_eq!(
        h.vertical_domain,
        Some(VerticalDomain::Time),
        "F3 says nothing: time"
    );
    h.vertical_domain = None;
    rewrite(2, &h);
    let v2 = PageStore::open(&path).unwrap();
    assert_eq!(v2.header(), &h, "a format 2 header reads back whole");
    h.stats = None;
    rewrite(1, &h);
    let old = PageStore::open(&path).unwrap();
    assert!(old.header().stats.is_none());
    assert!(old.header().vertical_domain.is_none());
    assert_eq!(old.header().dims, [23, 18, 75]);
    let text = inspect(&path, false, &ProgressBar::hidden()).unwrap().text;
    assert!(text.contains("statistics: none"), "{text}");
}
