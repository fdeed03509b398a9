use super::bytes::{put_i16, put_i32, put_u16};
use super::*;
use std::sync::atomic::{AtomicU64, Ordering};
use strata_common::geo::Affine2;

const F3_BE: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../shared/data/real/seismic/f3_segyio/f3.sgy"
);
const F3_LE: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../shared/data/real/seismic/f3_segyio/f3-lsb.sgy"
);
const F3_IBM: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../shared/data/real/seismic/f3_opendtect_very_small/F3_very_small.sgy"
);

/// A temporary file removed on drop.
struct Tmp(PathBuf);
impl Drop for Tmp {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}
fn tmp(name: &str) -> Tmp {
    static N: AtomicU64 = AtomicU64::new(0);
    let n = N.fetch_add(1, Ordering::Relaxed);
    Tmp(std::env::temp_dir().join(format!(
        "strata-segy-test-{}-{n}-{name}",
        std::process::id()
    )))
}
fn write_bytes(name: &str, bytes: &[u8]) -> Tmp {
    let t = tmp(name);
    std::fs::write(&t.0, bytes).unwrap();
    t
}

fn read_all(v: &SegyVolume) -> Vec<f32> {
    let d = v.dims();
    let mut out = vec![0.0; (d[0] * d[1] * d[2]) as usize];
    v.read_box([0; 3], d, &mut out).unwrap();
    out
}

fn stats(v: &[f32]) -> (f64, f64, f64, f64) {
    let n = v.len() as f64;
    let mean = v.iter().map(|&x| x as f64).sum::<f64>() / n;
    let var = v.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / n;
    let min = v.iter().fold(f32::INFINITY, |a, &b| a.min(b)) as f64;
    let max = v.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b)) as f64;
    (min, max, mean, var.sqrt())
}

fn err_of(r: Result<SegyVolume>) -> String {
    match r {
        Ok(_) => panic!("expected an error"),
        Err(e) => format!("{e}"),
    }
}

#[test]
fn three_byte_integer_formats_read_exactly_in_both_byte_orders() {
    // Rev 2 formats 7 (int24) and 15 (uint24), which segyio cannot read: the extremes,
    // both sides of zero and values past 16 bits come back exactly.
    let dir = tempfile::TempDir::new().unwrap();
    for (format, values) in [
        (
            7u16,
            vec![
                -8_388_608.0f32,
                8_388_607.0,
                -1.0,
                0.0,
                1.0,
                -65_537.0,
                123_456.0,
            ],
        ),
        (
            15u16,
            vec![
                0.0f32,
                16_777_215.0,
                1.0,
                65_536.0,
                8_388_608.0,
                255.0,
                70_000.0,
            ],
        ),
    ] {
        for endian in [Endian::Big, Endian::Little] {
            let p = dir.path().join(format!("f{format}-{endian:?}.sgy"));
            let n = values.len() as u32;
            let mut w = SegyWriter::create(&p, "C 1 int24", n, 2000, 0, format, endian).unwrap();
            for i in 0..2 {
                for j in 0..3 {
                    // Each trace its own rotation of the values.
                    let mut t = values.clone();
                    t.rotate_left(i * 3 + j);
                    w.write_trace(10 + i as i32, 20 + j as i32, i as f64, j as f64, &t)
                        .unwrap();
                }
            }
            w.finish().unwrap();
            let v = open(&p, &SegyOptions::default()).unwrap();
            assert_eq!(v.info().format_code, format);
            assert_eq!(v.info().bytes_per_sample, 3);
            assert_eq!(v.info().endian, endian);
            let mut out = vec![0.0f32; values.len()];
            for i in 0..2u64 {
                for j in 0..3u64 {
                    let t = v.trace_at(i, j).unwrap();
                    v.read_trace(t, &mut out).unwrap();
                    let mut want = values.clone();
                    want.rotate_left((i * 3 + j) as usize);
                    assert_eq!(out, want, "format {format} {endian:?} trace ({i}, {j})");
                }
            }
            // The strided path the store builder reads bricks through: a box of the
            // whole cube against the traces.
            let d = v.dims();
            let mut cube = vec![0.0f32; (d[0] * d[1] * d[2]) as usize];
            v.read_box([0, 0, 0], d, &mut cube).unwrap();
            for i in 0..d[0] {
                for j in 0..d[1] {
                    let t = v.trace_at(i, j).unwrap();
                    v.read_trace(t, &mut out).unwrap();
                    for k in 0..d[2] {
                        let got = cube[((k * d[1] + j) * d[0] + i) as usize];
                        assert_eq!(got, out[k as usize], "box ({i}, {j}, {k})");
                    }
                }
            }
        }
    }
}

#[test]
fn ibm_known_values() {
    assert_eq!(ibm_to_f32(0x4264_0000), 100.0);
    assert_eq!(ibm_to_f32(0xC276_A000), -118.625);
    assert_eq!(ibm_to_f32(0x0000_0000), 0.0);
    assert_eq!(ibm_to_f32(0x4110_0000), 1.0);
    assert_eq!(ibm_to_f32(0xC110_0000), -1.0);
    assert_eq!(ibm_to_f32(0x4080_0000), 0.5);
    assert_eq!(ibm_to_f32(0x4010_0000), 1.0 / 16.0);
    assert_eq!(ibm_to_f32(0x3F10_0000), 1.0 / 256.0);
    // Largest IBM value overflows f32; the smallest underflows to zero.
    assert_eq!(ibm_to_f32(0x7FFF_FFFF), f32::INFINITY);
    assert_eq!(ibm_to_f32(0x0010_0000), 0.0);
    // Unnormalized fractions decode too.
    assert_eq!(ibm_to_f32(0x4200_6400), 100.0 / 256.0);
    assert_eq!(f32_to_ibm(100.0), 0x4264_0000);
    assert_eq!(f32_to_ibm(-118.625), 0xC276_A000);
    assert_eq!(f32_to_ibm(0.0), 0);
    assert_eq!(f32_to_ibm(1.0), 0x4110_0000);
}

#[test]
fn ibm_round_trip() {
    // Values with at most 21 significant bits round-trip exactly; the rest within 2^-21.
    let mut s = 0x1234_5678_9abc_def0u64;
    let mut next = || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s
    };
    for k in -100_000i32..100_000 {
        let v = k as f32 * 0.125;
        assert_eq!(ibm_to_f32(f32_to_ibm(v)), v, "{v}");
    }
    let mut n = 0;
    while n < 200_000 {
        let v = f32::from_bits(next() as u32);
        if !v.is_normal() {
            continue;
        }
        n += 1;
        let back = ibm_to_f32(f32_to_ibm(v));
        let rel = ((back as f64 - v as f64) / v as f64).abs();
        assert!(rel <= 2f64.powi(-21), "{v:e} -> {back:e} ({rel:e})");
        let exact = f32::from_bits(v.to_bits() & !0x7); // 21 significant bits
        assert_eq!(ibm_to_f32(f32_to_ibm(exact)), exact, "{exact:e}");
    }
}

#[test]
fn cp037_table_is_a_permutation_and_text_round_trips() {
    let mut seen = [false; 256];
    for b in 0..=255u8 {
        let c = ebcdic_to_char(b);
        assert!(!seen[c as usize]);
        seen[c as usize] = true;
        assert_eq!(char_to_ebcdic(c), b);
    }
    assert_eq!(ebcdic_to_char(0xC3), 'C');
    assert_eq!(ebcdic_to_char(0x40), ' ');
    assert_eq!(ebcdic_to_char(0xF1), '1');
    assert_eq!(ebcdic_to_char(0x81), 'a');
    let text = "C 1 Hello (SEG-Y) world: x=1.5; ~ø\nC 2 second line";
    let enc = encode_text_header(text);
    assert_eq!(enc.len(), 3200);
    assert_eq!(decode_text_header(&enc), (text.to_string(), true));
    let mut ascii = vec![b' '; 3200];
    ascii[..10].copy_from_slice(b"C01 hello!");
    ascii[80..86].copy_from_slice(b"C02 ok");
    assert_eq!(
        decode_text_header(&ascii),
        ("C01 hello!\nC02 ok".to_string(), false)
    );
}

#[test]
fn f3_big_and_little_endian_agree() {
    let be = open(Path::new(F3_BE), &SegyOptions::default()).unwrap();
    let le = open(Path::new(F3_LE), &SegyOptions::default()).unwrap();
    assert_eq!(be.info().endian, Endian::Big);
    assert_eq!(le.info().endian, Endian::Little);
    for v in [&be, &le] {
        let i = v.info();
        assert_eq!(v.dims(), [23, 18, 75]);
        assert_eq!(v.contiguous_axis(), 2);
        assert_eq!(i.format_code, 3);
        assert_eq!(i.sample_type, SampleType::I16);
        assert_eq!(i.revision, (1, 0));
        assert!(i.fixed_length);
        assert_eq!(i.samples_per_trace, 75);
        assert_eq!(i.sample_interval_us, 4000);
        assert_eq!(i.trace_count, 414);
        assert_eq!(i.missing_traces, 0);
        assert_eq!(i.file_len, 165_060);
        assert_eq!(i.data_start, 3600);
        assert_eq!(i.trace_bytes, 240 + 75 * 2);
        assert_eq!(v.z_axis(), (4.0, 4.0));
        assert!(i.text_ebcdic);
        assert!(
            i.text_header
                .starts_with("C 1 Cropped F3 2-byte integer data set\n"),
            "{}",
            i.text_header
        );
        assert!(i.text_header.contains("C 7     crosslines: 875 .. 892"));
        let s = &i.survey;
        assert_eq!((s.inline0, s.inline_step, s.n_inline), (111.0, 1.0, 23));
        assert_eq!((s.xline0, s.xline_step, s.n_xline), (875.0, 1.0, 18));
        // The 462-vs-75 quirk is resolved by the file size, with a warning.
        assert_eq!(i.warnings.len(), 1, "{:?}", i.warnings);
        let w = &i.warnings[0];
        assert!(
            w.contains("462") && w.contains("75") && w.contains("trusted the binary header"),
            "{w}"
        );
        // Coordinates: CDP with scalar -10; first trace at (620197.2, 6074232.9).
        assert_eq!(i.coordinates, "CDP");
        let fit = i.fit.unwrap();
        let w00 = s.to_world.apply([0.0, 0.0]);
        assert!(
            (w00[0] - 620197.2).abs() <= fit.max_residual + 1e-6,
            "{w00:?} {fit:?}"
        );
        assert!(
            (w00[1] - 6074232.9).abs() <= fit.max_residual + 1e-6,
            "{w00:?} {fit:?}"
        );
        assert!(fit.max_residual < 1.0, "{fit:?}");
        let mut t = vec![0.0; 75];
        v.read_trace(0, &mut t).unwrap();
        let all = read_all(v);
        assert_eq!(
            &t[..],
            &all.iter().step_by(23 * 18).copied().collect::<Vec<_>>()[..]
        );
    }
    let (a, b) = (read_all(&be), read_all(&le));
    assert_eq!(a, b);
    let (min, max, mean, std) = stats(&a);
    assert_eq!((min, max), (-10239.0, 10827.0));
    assert!((mean - 25.13).abs() < 0.01, "{mean}");
    assert!((std - 2160.21).abs() / 2160.21 < 1e-4, "{std}");
    // Every trace identical in both files, trace by trace.
    let mut tb = vec![0.0; 75];
    let mut tl = vec![0.0; 75];
    for t in 0..414 {
        be.read_trace(t, &mut tb).unwrap();
        le.read_trace(t, &mut tl).unwrap();
        assert_eq!(tb, tl, "trace {t}");
    }
}

#[test]
fn f3_sub_boxes_match_the_full_read() {
    let v = open(Path::new(F3_BE), &SegyOptions::default()).unwrap();
    let all = read_all(&v);
    let d = v.dims();
    for (lo, size) in [
        ([0, 0, 0], [1, 1, 1]),
        ([3, 5, 10], [7, 4, 20]),
        ([22, 17, 74], [1, 1, 1]),
        ([0, 2, 0], [23, 1, 75]),
    ] {
        let mut out = vec![0.0; (size[0] * size[1] * size[2]) as usize];
        v.read_box(lo, size, &mut out).unwrap();
        for z in 0..size[2] {
            for y in 0..size[1] {
                for x in 0..size[0] {
                    let o = ((z * size[1] + y) * size[0] + x) as usize;
                    let a = (((lo[2] + z) * d[1] + lo[1] + y) * d[0] + lo[0] + x) as usize;
                    assert_eq!(out[o], all[a]);
                }
            }
        }
    }
    // Boxes outside the volume or a wrong buffer size are errors, not panics.
    let mut out = vec![0.0; 8];
    assert!(v.read_box([22, 0, 0], [2, 2, 2], &mut out).is_err());
    assert!(v.read_box([0, 0, 0], [2, 2, 3], &mut out).is_err());
    assert!(v.read_box([u64::MAX, 0, 0], [2, 2, 2], &mut out).is_err());
    fn assert_sync<T: Sync>(_: &T) {}
    assert_sync(&v);
}

#[test]
fn f3_forced_wrong_endian_is_a_clear_error() {
    let opts = SegyOptions {
        endian: Some(Endian::Little),
        ..Default::default()
    };
    let e = err_of(open(Path::new(F3_BE), &opts));
    assert!(
        e.contains("f3.sgy") && e.contains("3224") && e.contains("768"),
        "{e}"
    );
    let opts = SegyOptions {
        endian: Some(Endian::Big),
        ..Default::default()
    };
    assert_eq!(
        open(Path::new(F3_BE), &opts).unwrap().info().endian,
        Endian::Big
    );
}

#[test]
fn f3_ibm_opendtect() {
    let v = open(Path::new(F3_IBM), &SegyOptions::default()).unwrap();
    let i = v.info();
    assert_eq!(v.dims(), [11, 11, 463]);
    assert_eq!(i.endian, Endian::Big);
    assert_eq!(i.format_code, 1);
    assert_eq!(i.sample_type, SampleType::F32);
    assert_eq!(i.revision, (1, 0));
    assert_eq!(v.z_axis(), (0.0, 4.0));
    assert!(!i.text_ebcdic);
    assert!(
        i.text_header.contains("C02  Survey: 'F3 Demo'"),
        "{}",
        i.text_header
    );
    assert!(i.text_header.contains("C40  END TEXTUAL HEADER"));
    assert!(i.warnings.is_empty(), "{:?}", i.warnings);
    let s = &i.survey;
    assert_eq!((s.inline0, s.inline_step, s.n_inline), (200.0, 1.0, 11));
    assert_eq!((s.xline0, s.xline_step, s.n_xline), (400.0, 1.0, 11));
    let w00 = s.to_world.apply([0.0, 0.0]);
    assert!(
        (w00[0] - 608264.7).abs() < 1.0 && (w00[1] - 6076125.2).abs() < 1.0,
        "{w00:?}"
    );
    let (min, max, mean, std) = stats(&read_all(&v));
    assert_eq!((min, max), (-16032.0, 10745.0));
    assert!((mean - 1.368).abs() / 1.368 < 1e-3, "{mean}");
    assert!((std - 2404.42).abs() / 2404.42 < 1e-3, "{std}");
}

/// Writes a rotated UTM grid (inline step 2, crossline step 3) with some traces left out.
fn synth(format: u16, endian: Endian) -> (Tmp, Vec<(u64, u64)>) {
    let t = tmp(&format!("synth-{format}-{endian:?}.sgy"));
    let (ni, nx, ns) = (7u64, 9u64, 50usize);
    let skip = [(1, 1), (2, 5), (3, 3), (6, 0), (6, 1)];
    let text = "C 1 Synthetic test survey\nC 2 rotated 30 degrees";
    let mut w = SegyWriter::create(&t.0, text, ns as u32, 2000, 100, format, endian).unwrap();
    let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
    // Crossline-major order: the reader must not assume inline sorting.
    for j in 0..nx {
        for i in 0..ni {
            if skip.contains(&(i, j)) {
                continue;
            }
            let (fi, fj) = (i as f64, j as f64);
            let x = 612_345.6 + 25.0 * c * fi - 12.5 * s * fj;
            let y = 6_078_901.2 + 25.0 * s * fi + 12.5 * c * fj;
            let samples: Vec<f32> = (0..ns).map(|k| synth_value(i, j, k as u64)).collect();
            w.write_trace(1000 + 2 * i as i32, 2000 + 3 * j as i32, x, y, &samples)
                .unwrap();
        }
    }
    w.finish().unwrap();
    (t, skip.to_vec())
}

fn synth_value(i: u64, j: u64, k: u64) -> f32 {
    ((i * 31 + j * 17 + k * 7) % 200) as f32 * 13.7 - 1000.0 + 0.3
}

#[test]
fn writer_reader_round_trip() {
    for format in [1u16, 3, 5] {
        for endian in [Endian::Big, Endian::Little] {
            let (t, skip) = synth(format, endian);
            let v = open(&t.0, &SegyOptions::default()).unwrap();
            let i = v.info();
            assert_eq!(v.dims(), [7, 9, 50]);
            assert_eq!(i.endian, endian);
            assert_eq!(i.format_code, format);
            assert_eq!(
                i.sample_type,
                if format == 3 {
                    SampleType::I16
                } else {
                    SampleType::F32
                }
            );
            assert_eq!(i.revision, (1, 0));
            assert_eq!(v.z_axis(), (100.0, 2.0));
            assert!(i.text_ebcdic);
            assert_eq!(
                i.text_header,
                "C 1 Synthetic test survey\nC 2 rotated 30 degrees"
            );
            assert_eq!(i.trace_count, 58);
            assert_eq!(i.missing_traces, 5);
            assert_eq!(i.warnings.len(), 1, "{:?}", i.warnings);
            assert!(i.warnings[0].contains("5 of 63"), "{:?}", i.warnings);
            let s = &i.survey;
            assert_eq!((s.inline0, s.inline_step, s.n_inline), (1000.0, 2.0, 7));
            assert_eq!((s.xline0, s.xline_step, s.n_xline), (2000.0, 3.0, 9));
            assert_eq!(s.index_of(1004.0, 2009.0), Some((2, 3)));
            let fit = i.fit.unwrap();
            assert!(fit.max_residual < 0.01, "{fit:?}"); // centimetre rounding only
            let (c, sn) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
            let w = s.to_world.apply([4.0, 6.0]);
            let truth = [
                612_345.6 + 100.0 * c - 75.0 * sn,
                6_078_901.2 + 100.0 * sn + 75.0 * c,
            ];
            assert!(
                (w[0] - truth[0]).abs() < 0.01 && (w[1] - truth[1]).abs() < 0.01,
                "{w:?} {truth:?}"
            );
            let all = read_all(&v);
            for k in 0..50u64 {
                for jj in 0..9u64 {
                    for ii in 0..7u64 {
                        let got = all[((k * 9 + jj) * 7 + ii) as usize];
                        if skip.contains(&(ii, jj)) {
                            assert!(got.is_nan());
                            assert_eq!(v.trace_at(ii, jj), None);
                            continue;
                        }
                        let want = synth_value(ii, jj, k);
                        match format {
                            3 => assert_eq!(got, want.round()),
                            5 => assert_eq!(got, want),
                            _ => assert!(
                                (got - want).abs() <= want.abs() * 2f32.powi(-20),
                                "{got} {want}"
                            ),
                        }
                    }
                }
            }
        }
    }
}

#[test]
fn alternate_line_number_bytes() {
    let (t, _) = synth(5, Endian::Big);
    let a = open(&t.0, &SegyOptions::default()).unwrap();
    let b = open(
        &t.0,
        &SegyOptions {
            inline_byte: 9,
            xline_byte: 21,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(a.info().survey, b.info().survey);
    assert_eq!(
        read_all(&a).iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
        read_all(&b).iter().map(|v| v.to_bits()).collect::<Vec<_>>()
    );
    let e = err_of(open(
        &t.0,
        &SegyOptions {
            inline_byte: 239,
            ..Default::default()
        },
    ));
    assert!(e.contains("239"), "{e}");
    // Trace sequence numbers (bytes 1 and 5) as line numbers: every trace on one
    // inline and crossline pair → duplicates.
    let e = err_of(open(
        &t.0,
        &SegyOptions {
            inline_byte: 13,
            xline_byte: 13,
            ..Default::default()
        },
    ));
    assert!(
        e.contains("duplicate")
            && e.contains("trace 1 at byte 3600")
            && e.contains("trace 2 at byte"),
        "{e}"
    );
}

#[test]
fn extended_textual_headers_are_skipped() {
    let (t, _) = synth(5, Endian::Little);
    let base = std::fs::read(&t.0).unwrap();
    let want = read_all(&open(&t.0, &SegyOptions::default()).unwrap());
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    // Two extended headers, counted.
    let mut f = base[..3600].to_vec();
    put_i16(&mut f, 3505, 2, Endian::Little);
    f.extend(encode_text_header("extended 1"));
    f.extend(encode_text_header("extended 2"));
    f.extend_from_slice(&base[3600..]);
    let t2 = write_bytes("ext2.sgy", &f);
    let v = open(&t2.0, &SegyOptions::default()).unwrap();
    assert_eq!(v.info().extended_text_headers, 2);
    assert_eq!(v.info().data_start, 3600 + 6400);
    assert_eq!(bits(&read_all(&v)), bits(&want));
    // -1: scan to the EndText stanza (ASCII here).
    let mut f = base[..3600].to_vec();
    put_i16(&mut f, 3505, -1, Endian::Little);
    f.extend(vec![b' '; 3200]);
    let mut last = vec![b' '; 3200];
    last[..END_TEXT.len()].copy_from_slice(END_TEXT.as_bytes());
    f.extend(last);
    f.extend_from_slice(&base[3600..]);
    let t3 = write_bytes("ext-1.sgy", &f);
    let v = open(&t3.0, &SegyOptions::default()).unwrap();
    assert_eq!(v.info().extended_text_headers, 2);
    assert_eq!(bits(&read_all(&v)), bits(&want));
    // -1 without a stanza.
    let mut f = base.clone();
    put_i16(&mut f, 3505, -1, Endian::Little);
    let t4 = write_bytes("ext-none.sgy", &f);
    let e = err_of(open(&t4.0, &SegyOptions::default()));
    assert!(e.contains("ext-none.sgy") && e.contains("EndText"), "{e}");
}

#[test]
fn byte_order_constant_decides() {
    // A big-endian file whose format code would also read as valid little-endian is
    // impossible, so check that the constant wins over an explicit-looking format code:
    // a little-endian file marked with the constant still reads as little-endian.
    let (t, _) = synth(3, Endian::Little);
    let mut f = std::fs::read(&t.0).unwrap();
    f[3296..3300].copy_from_slice(&0x0102_0304u32.to_le_bytes());
    let t2 = write_bytes("bo.sgy", &f);
    assert_eq!(
        open(&t2.0, &SegyOptions::default()).unwrap().info().endian,
        Endian::Little
    );
    // The constant written big-endian on the same file forces big-endian: format code
    // then reads 0x0300 and is rejected.
    f[3296..3300].copy_from_slice(&0x0102_0304u32.to_be_bytes());
    let t3 = write_bytes("bo2.sgy", &f);
    let e = err_of(open(&t3.0, &SegyOptions::default()));
    assert!(e.contains("bo2.sgy") && e.contains("768"), "{e}");
}

#[test]
fn truncated_files_are_errors() {
    let base = std::fs::read(F3_BE).unwrap();
    let t = write_bytes("trunc.sgy", &base[..base.len() - 100]);
    let e = err_of(open(&t.0, &SegyOptions::default()));
    // Trace 414 starts at 3600 + 413 * 390 = 164670.
    assert!(
        e.contains("trunc.sgy")
            && e.contains("truncated")
            && e.contains("trace 414 at byte 164670"),
        "{e}"
    );
    assert!(
        e.contains("needs 390 bytes") && e.contains("file has 290"),
        "{e}"
    );
    assert!(!e.contains('\n'));
    // Headers only; then less than the headers; then empty.
    for (n, what) in [
        (3600usize, "no traces"),
        (3000, "not a SEG-Y"),
        (0, "not a SEG-Y"),
    ] {
        let t = write_bytes("short.sgy", &base[..n]);
        let e = err_of(open(&t.0, &SegyOptions::default()));
        assert!(e.contains("short.sgy") && e.contains(what), "{e}");
    }
    let e = err_of(open(
        Path::new("/nonexistent/dir/x.sgy"),
        &SegyOptions::default(),
    ));
    assert!(e.contains("/nonexistent/dir/x.sgy"), "{e}");
}

#[test]
fn sample_count_disagreement_that_nothing_confirms() {
    let mut f = std::fs::read(F3_BE).unwrap();
    put_u16(&mut f, 3221, 80, Endian::Big);
    let t = write_bytes("ns.sgy", &f);
    let e = err_of(open(&t.0, &SegyOptions::default()));
    assert!(
        e.contains("ns.sgy") && e.contains("80") && e.contains("462") && e.contains("neither"),
        "{e}"
    );
    // Binary header 0: the trace header (462) does not fit either → truncated.
    put_u16(&mut f, 3221, 0, Endian::Big);
    let t = write_bytes("ns0.sgy", &f);
    let e = err_of(open(&t.0, &SegyOptions::default()));
    assert!(e.contains("ns0.sgy") && e.contains("truncated"), "{e}");
    // Binary header 0 and the trace headers right: trusted, with a warning.
    let (t, _) = synth(5, Endian::Big);
    let mut f = std::fs::read(&t.0).unwrap();
    put_u16(&mut f, 3221, 0, Endian::Big);
    let t2 = write_bytes("ns-tr.sgy", &f);
    let v = open(&t2.0, &SegyOptions::default()).unwrap();
    assert_eq!(v.dims(), [7, 9, 50]);
    assert!(
        v.info()
            .warnings
            .iter()
            .any(|w| w.contains("trusted the trace header")),
        "{:?}",
        v.info().warnings
    );
}

#[test]
fn unknown_format_codes_are_errors() {
    for code in [4u16, 99, 0] {
        let mut f = std::fs::read(F3_BE).unwrap();
        put_u16(&mut f, 3225, code, Endian::Big);
        let t = write_bytes(&format!("fmt{code}.sgy"), &f);
        let e = err_of(open(&t.0, &SegyOptions::default()));
        assert!(
            e.contains(&format!("fmt{code}.sgy")) && e.contains("3224"),
            "{e}"
        );
        assert!(
            e.contains(&format!(" {code} ")) && e.contains("supported: 1 (4-byte IBM float)"),
            "{e}"
        );
    }
}

#[test]
fn garbage_headers_are_errors() {
    let base = std::fs::read(F3_BE).unwrap();
    let mut f = base.clone();
    f[3200..3600].fill(0xFF);
    let t = write_bytes("garbage-ff.sgy", &f);
    let e = err_of(open(&t.0, &SegyOptions::default()));
    assert!(e.contains("garbage-ff.sgy") && e.contains("3224"), "{e}");
    let mut s = 0x9E37_79B9_7F4A_7C15u64;
    for b in &mut f[3200..3600] {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        *b = (s >> 56) as u8;
    }
    let t = write_bytes("garbage-rand.sgy", &f);
    let e = err_of(open(&t.0, &SegyOptions::default()));
    assert!(e.contains("garbage-rand.sgy"), "{e}");
    // Garbage inline numbers: a huge sparse grid is rejected, not allocated.
    let mut f = base.clone();
    put_i32(&mut f, 3600 + 188 + 1, 2_000_000_000, Endian::Big);
    let t = write_bytes("garbage-il.sgy", &f);
    let e = err_of(open(&t.0, &SegyOptions::default()));
    assert!(
        e.contains("garbage-il.sgy") && e.contains("grid") && e.contains("189"),
        "{e}"
    );
}

#[test]
fn degenerate_geometry_falls_back_to_index_grid() {
    let write = |name: &str, ni: i32, nx: i32, coords: bool| {
        let t = tmp(name);
        let mut w = SegyWriter::create(&t.0, "C 1 x", 4, 4000, 0, 5, Endian::Big).unwrap();
        for i in 0..ni {
            for j in 0..nx {
                let (x, y) = if coords {
                    (500_000.0 + 25.0 * j as f64, 6_000_000.0 + 10.0 * i as f64)
                } else {
                    (0.0, 0.0)
                };
                w.write_trace(10 + i, 20 + j, x, y, &[1.0, 2.0, 3.0, 4.0])
                    .unwrap();
            }
        }
        w.finish().unwrap();
        t
    };
    // A single inline: no 2D fit.
    let t = write("one-line.sgy", 1, 5, true);
    let v = open(&t.0, &SegyOptions::default()).unwrap();
    assert_eq!(v.dims(), [1, 5, 4]);
    assert!(v.info().fit.is_none());
    assert_eq!(v.info().survey.to_world, Affine2::IDENTITY);
    assert!(
        v.info().warnings.iter().any(|w| w.contains("cannot place")),
        "{:?}",
        v.info().warnings
    );
    // All-zero coordinates.
    let t = write("zero-xy.sgy", 3, 3, false);
    let v = open(&t.0, &SegyOptions::default()).unwrap();
    assert_eq!(v.dims(), [3, 3, 4]);
    assert_eq!(v.info().coordinates, "none");
    assert!(v.info().fit.is_none());
    assert_eq!(v.info().survey.to_world, Affine2::IDENTITY);
    assert!(
        v.info().warnings.iter().any(|w| w.contains("all zero")),
        "{:?}",
        v.info().warnings
    );
    // A regular grid in source X/Y only (CDP zeroed): placed from source coordinates.
    let t = write("src-xy.sgy", 3, 4, true);
    let mut f = std::fs::read(&t.0).unwrap();
    for k in 0..12 {
        let h = 3600 + k * (240 + 16);
        f[h + 180..h + 188].fill(0);
    }
    std::fs::write(&t.0, &f).unwrap();
    let v = open(&t.0, &SegyOptions::default()).unwrap();
    assert_eq!(v.info().coordinates, "source");
    assert!(v.info().fit.unwrap().max_residual < 1e-6);
    assert_eq!(
        v.info().survey.to_world.apply([2.0, 3.0]),
        [500_075.0, 6_000_020.0]
    );
    // A rev 0 file with garbage where rev 1 keeps the extended-header count.
    let mut g = f.clone();
    g[3500] = 0;
    put_i16(&mut g, 3505, 77, Endian::Big);
    std::fs::write(&t.0, &g).unwrap();
    let v = open(&t.0, &SegyOptions::default()).unwrap();
    assert_eq!(
        (v.info().revision, v.info().extended_text_headers, v.dims()),
        ((0, 0), 0, [3, 4, 4])
    );
}

#[test]
fn mutated_files_never_panic() {
    let (t, _) = synth(1, Endian::Big);
    let base = std::fs::read(&t.0).unwrap();
    let mut s = 0x0123_4567_89AB_CDEFu64;
    let mut rnd = move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        s >> 33
    };
    let out = tmp("fuzz.sgy");
    let (mut ok, mut err) = (0, 0);
    for it in 0..400 {
        let mut f = base.clone();
        for _ in 0..1 + rnd() % 8 {
            // Mostly the binary header and the first trace headers.
            let pos = match rnd() % 3 {
                0 => 3200 + rnd() % 400,
                1 => 3600 + rnd() % 240,
                _ => rnd() % f.len() as u64,
            } as usize;
            f[pos] = rnd() as u8;
        }
        if it % 5 == 0 {
            f.truncate(rnd() as usize % f.len());
        }
        std::fs::write(&out.0, &f).unwrap();
        match open(&out.0, &SegyOptions::default()) {
            Ok(v) => {
                ok += 1;
                let d = v.dims();
                if d.iter().product::<u64>() < 10_000_000 {
                    let _ = read_all(&v);
                }
            }
            Err(e) => {
                err += 1;
                let m = format!("{e}");
                assert!(m.contains("fuzz.sgy") && !m.contains('\n'), "{m}");
            }
        }
    }
    assert!(ok > 0 && err > 0, "{ok} {err}");
}

/// A 3 x 4 post-stack file with `text` as its textual header, `dt` in the sample-interval
/// field and `delay` at byte 109; `patch` edits its bytes before it is written.
fn small(name: &str, text: &str, dt: u32, delay: i16, patch: impl FnOnce(&mut Vec<u8>)) -> Tmp {
    let t = tmp(name);
    let mut w = SegyWriter::create(&t.0, text, 20, dt, delay, 5, Endian::Big).unwrap();
    for i in 0..3 {
        for j in 0..4 {
            let s: Vec<f32> = (0..20).map(|k| (i * 100 + j * 10 + k) as f32).collect();
            w.write_trace(
                10 + i,
                20 + j,
                1000.0 + 25.0 * i as f64,
                500.0 + 25.0 * j as f64,
                &s,
            )
            .unwrap();
        }
    }
    w.finish().unwrap();
    let mut b = std::fs::read(&t.0).unwrap();
    patch(&mut b);
    std::fs::write(&t.0, &b).unwrap();
    t
}

fn open_with(t: &Tmp, f: impl FnOnce(&mut SegyOptions)) -> Result<SegyVolume> {
    let mut o = SegyOptions::default();
    f(&mut o);
    open(&t.0, &o)
}

#[test]
fn depth_cubes_are_read_as_depth_in_their_unit() {
    // The text says depth and feet: 5000 in the sample-interval field is 5 ft per sample.
    let t = small(
        "psdm-ft.sgy",
        "C 1 KIRCHHOFF PSDM\nC 2 DEPTH IN FEET",
        5000,
        1500,
        |_| {},
    );
    let v = open(&t.0, &SegyOptions::default()).unwrap();
    let a = &v.info().vertical;
    assert_eq!(
        (a.domain, a.unit),
        (VerticalDomain::Depth, VerticalUnit::Ft)
    );
    assert_eq!(v.z_axis(), (1500.0, 5.0));
    assert!(
        a.domain_from.contains("line 1") && a.domain_from.contains("PSDM"),
        "{}",
        a.domain_from
    );
    assert!(a.unit_from.contains("feet"), "{}", a.unit_from);
    assert!(v.info().warnings.is_empty(), "{:?}", v.info().warnings);

    // Depth said in words, unit only in the binary header's measurement system (3255).
    for (system, unit) in [(1u16, VerticalUnit::M), (2, VerticalUnit::Ft)] {
        let t = small(
            "depth-sys.sgy",
            "C 1 DEPTH MIGRATED VOLUME",
            12500,
            0,
            |b| put_u16(b, 3255, system, Endian::Big),
        );
        let v = open(&t.0, &SegyOptions::default()).unwrap();
        assert_eq!(v.info().vertical.unit, unit);
        assert!(v.info().vertical.unit_from.contains("3255"));
        assert_eq!(v.z_axis().1, 12.5);
    }
    // No measurement system: metres, with a warning that says how to say feet.
    let t = small("depth-nosys.sgy", "C 1 DEPTH DOMAIN", 10000, 0, |b| {
        put_u16(b, 3255, 0, Endian::Big)
    });
    let v = open(&t.0, &SegyOptions::default()).unwrap();
    assert_eq!(v.info().vertical.unit, VerticalUnit::M);
    assert!(
        v.info()
            .warnings
            .iter()
            .any(|w| w.contains("--vertical-unit ft")),
        "{:?}",
        v.info().warnings
    );

    // Rev 2's extended sample interval (3273, IEEE double, thousandths) wins.
    let t = small("depth-rev2.sgy", "C 1 DEPTH DATA", 6000, 0, |b| {
        b[3500] = 2;
        b[3272..3280].copy_from_slice(&6250.0f64.to_be_bytes());
    });
    let v = open(&t.0, &SegyOptions::default()).unwrap();
    assert_eq!(v.z_axis().1, 6.25);
}

#[test]
fn time_is_assumed_only_when_nothing_says_otherwise() {
    // F3 says nothing: time in ms, 4 ms samples, and the reason is recorded, not warned.
    let v = open(Path::new(F3_BE), &SegyOptions::default()).unwrap();
    let a = &v.info().vertical;
    assert_eq!((a.domain, a.unit), (VerticalDomain::Time, VerticalUnit::Ms));
    assert_eq!(a.domain_from, ASSUMED_TIME);
    assert_eq!(v.z_axis().1, 4.0);
    // The same file forced to depth (its binary header says metres).
    let v = open(
        Path::new(F3_BE),
        &SegyOptions {
            vertical: Some(VerticalDomain::Depth),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(
        (v.info().vertical.domain, v.info().vertical.unit),
        (VerticalDomain::Depth, VerticalUnit::M)
    );
    assert_eq!(v.info().vertical.domain_from, "--vertical");

    // Time said in words; seconds on request: 2000 us is 0.002 s, a delay of 100 ms 0.1 s.
    let t = small("twt.sgy", "C 1 PSTM STACK\nC 2 Z: TWT", 2000, 100, |_| {});
    let v = open(&t.0, &SegyOptions::default()).unwrap();
    assert_eq!(v.info().vertical.domain, VerticalDomain::Time);
    assert_eq!(v.z_axis(), (100.0, 2.0));
    let v = open_with(&t, |o| o.vertical_unit = Some(VerticalUnit::S)).unwrap();
    assert_eq!(v.z_axis(), (0.1, 0.002));
    // A depth unit alone makes the cube depth.
    let v = open_with(&t, |o| {
        o.vertical = None;
        o.vertical_unit = Some(VerticalUnit::M)
    })
    .unwrap();
    assert_eq!(v.info().vertical.domain, VerticalDomain::Depth);
    // ... against what the headers say, which is worth a warning.
    assert!(
        v.info()
            .warnings
            .iter()
            .any(|w| w.contains("--vertical-unit m makes the traces depth")),
        "{:?}",
        v.info().warnings
    );
    // --z-step overrides the field.
    let v = open_with(&t, |o| o.z_step = Some(0.5)).unwrap();
    assert_eq!(v.z_axis().1, 0.5);

    // The rev 1 time scalar (bytes 215-216) scales the delay: -10 divides.
    let t = small("scaled-delay.sgy", "C 1 TWT", 4000, 1234, |b| {
        for k in 0..12 {
            put_i16(b, 3600 + k * (240 + 80) + 215, -10, Endian::Big);
        }
    });
    let v = open(&t.0, &SegyOptions::default()).unwrap();
    assert!((v.z_axis().0 - 123.4).abs() < 1e-9, "{:?}", v.z_axis());
}

#[test]
fn vertical_contradictions_are_clear_errors() {
    let t = small("both.sgy", "C 1 PSDM\nC 2 TIME MIGRATED", 4000, 0, |_| {});
    let e = err_of(open(&t.0, &SegyOptions::default()));
    assert!(
        e.contains("both.sgy")
            && e.contains("both depth")
            && e.contains("line 1")
            && e.contains("line 2")
            && e.contains("--vertical"),
        "{e}"
    );
    // The options settle it.
    let v = open_with(&t, |o| o.vertical = Some(VerticalDomain::Depth)).unwrap();
    assert_eq!(v.info().vertical.domain, VerticalDomain::Depth);
    let e = err_of(open_with(&t, |o| {
        o.vertical = Some(VerticalDomain::Time);
        o.vertical_unit = Some(VerticalUnit::Ft)
    }));
    assert!(e.contains("--vertical-unit ft is a depth unit"), "{e}");
    // Bare time words are weak: a PSDM header that gives its interval in msec is depth.
    let t = small(
        "weak.sgy",
        "C 1 PSDM\nC 2 SAMPLE INTERVAL 4 MSEC",
        4000,
        0,
        |_| {},
    );
    let v = open(&t.0, &SegyOptions::default()).unwrap();
    assert_eq!(v.info().vertical.domain, VerticalDomain::Depth);
    assert!(
        v.info().warnings.iter().any(|w| w.contains("mention time")),
        "{:?}",
        v.info().warnings
    );
    for bad in [0.0, -1.0, 1e-320, 1e12, f64::NAN, f64::INFINITY] {
        let e = err_of(open_with(&t, |o| {
            o.vertical = Some(VerticalDomain::Depth);
            o.z_step = Some(bad)
        }));
        assert!(e.contains("--z-step"), "{e}");
    }
}

#[test]
fn extended_text_headers_can_say_depth() {
    // Two extended headers; the second says depth.
    let t = small("ext-depth.sgy", "C 1 nothing here", 5000, 0, |b| {
        let mut ext = encode_text_header("C 1 first extended");
        ext.extend(encode_text_header(
            "((SEG: Processing))\nC 2 DEPTH CUBE AFTER PSDM",
        ));
        b.splice(3600..3600, ext);
        b[3500] = 1;
        put_i16(b, 3505, 2, Endian::Big);
    });
    let v = open(&t.0, &SegyOptions::default()).unwrap();
    assert_eq!(v.info().extended_text_headers, 2);
    assert_eq!(v.info().vertical.domain, VerticalDomain::Depth);
    // Line 40 + 40 + 2 of the text headers.
    assert!(
        v.info().vertical.domain_from.contains("line 82"),
        "{}",
        v.info().vertical.domain_from
    );
}

/// A pre-stack file: 3 x 4 nodes, offsets 100, 200, 300 at each (300 missing at node
/// (1, 2)), sample k of offset o at node (i, j) = i·1000 + j·100 + o + k.
fn prestack(name: &str) -> Tmp {
    let t = tmp(name);
    let mut w = SegyWriter::create(&t.0, "C 1 CMP gathers", 8, 4000, 0, 5, Endian::Little).unwrap();
    for i in 0..3i32 {
        for j in 0..4i32 {
            for o in [100, 200, 300] {
                if (i, j, o) == (1, 2, 300) {
                    continue;
                }
                w.set_offset(o);
                let s: Vec<f32> = (0..8)
                    .map(|k| (i * 1000 + j * 100 + o + k) as f32)
                    .collect();
                w.write_trace(i + 1, j + 1, 100.0 * i as f64, 50.0 * j as f64, &s)
                    .unwrap();
            }
        }
    }
    w.finish().unwrap();
    t
}

#[test]
fn prestack_files_are_named_and_read_by_offset_or_stacked() {
    let t = prestack("gathers.sgy");
    let e = err_of(open(&t.0, &SegyOptions::default()));
    assert!(
        e.contains("gathers.sgy")
            && e.contains("pre-stack")
            && e.contains("3 distinct offsets")
            && e.contains("100, 200, 300")
            && e.contains("--offset N")
            && e.contains("--stack")
            && !e.contains("duplicate"),
        "{e}"
    );

    // One offset: the exact samples of that offset; the node without it is no-data.
    let v = open_with(&t, |o| o.offset = Some(300)).unwrap();
    let i = v.info();
    assert_eq!(
        (i.trace_count, i.traces_used, i.max_fold, i.distinct_offsets),
        (35, 11, 1, 3)
    );
    assert_eq!(i.missing_traces, 1);
    assert_eq!(i.sample_type, SampleType::F32);
    let all = read_all(&v);
    let d = v.dims();
    let at = |all: &[f32], i: u64, j: u64, k: u64| all[(k * d[1] * d[0] + j * d[0] + i) as usize];
    for ii in 0..3 {
        for jj in 0..4 {
            for k in 0..8 {
                let got = at(&all, ii, jj, k);
                if (ii, jj) == (1, 2) {
                    assert!(got.is_nan());
                } else {
                    assert_eq!(got, (ii * 1000 + jj * 100 + 300 + k) as f32);
                }
            }
        }
    }
    assert_eq!(
        v.trace_at(0, 0),
        Some(2),
        "offset 300 of the first gather is trace 3"
    );

    // The stack: the mean of each gather, whatever its fold.
    let v = open_with(&t, |o| o.stack = true).unwrap();
    assert!(v.info().stacked && v.info().max_fold == 3 && v.info().missing_traces == 0);
    let all = read_all(&v);
    for ii in 0..3 {
        for jj in 0..4 {
            for k in 0..8 {
                let mean = if (ii, jj) == (1, 2) { 150.0 } else { 200.0 };
                assert_eq!(
                    at(&all, ii, jj, k),
                    (ii * 1000 + jj * 100 + k) as f32 + mean
                );
            }
        }
    }
    // A sub-box of the stack equals the same part of the whole.
    let mut part = vec![0.0; 2 * 2 * 3];
    v.read_box([1, 1, 4], [2, 2, 3], &mut part).unwrap();
    for (n, &p) in part.iter().enumerate() {
        let (i, j, k) = (1 + n as u64 % 2, 1 + (n as u64 / 2) % 2, 4 + n as u64 / 4);
        assert_eq!(p, at(&all, i, j, k));
    }

    let e = err_of(open_with(&t, |o| o.offset = Some(250)));
    assert!(
        e.contains("--offset 250") && e.contains("100, 200, 300"),
        "{e}"
    );
    let e = err_of(open_with(&t, |o| {
        o.offset = Some(100);
        o.stack = true
    }));
    assert!(e.contains("--offset and --stack"), "{e}");
}

#[test]
fn duplicates_at_one_offset_are_not_called_pre_stack() {
    // Every trace written twice with the same offset: a duplicate, not a gather.
    let t = tmp("dups.sgy");
    let mut w = SegyWriter::create(&t.0, "C 1 dups", 4, 4000, 0, 5, Endian::Big).unwrap();
    for i in 0..2 {
        for j in 0..2 {
            for _ in 0..2 {
                w.write_trace(
                    i,
                    j,
                    i as f64 * 10.0,
                    j as f64 * 10.0,
                    &[1.0, 2.0, 3.0, 4.0],
                )
                .unwrap();
            }
        }
    }
    w.finish().unwrap();
    let e = err_of(open(&t.0, &SegyOptions::default()));
    assert!(
        e.contains("duplicate trace") && !e.contains("pre-stack") && e.contains("--stack"),
        "{e}"
    );
    // Stacking identical traces gives the trace.
    let v = open_with(&t, |o| o.stack = true).unwrap();
    assert_eq!(
        read_all(&v),
        [1.0, 1.0, 1.0, 1.0, 2.0, 2.0, 2.0, 2.0, 3.0, 3.0, 3.0, 3.0, 4.0, 4.0, 4.0, 4.0]
    );
}

/// Rev 2: a trace longer than 65535 samples gives its length in the extended count (bytes
/// 3269-3272), which overrides the 16-bit one even where a writer left that saturated at
/// 65535 (the file had been refused: neither length fitted its size).
#[test]
fn rev2_extended_sample_count_overrides_a_saturated_16_bit_one() {
    let t = tmp("rev2-long.sgy");
    let ns = 70_000usize;
    let small = tmp("rev2-seed.sgy");
    let mut w =
        SegyWriter::create(&small.0, "C 1 long traces", 4, 2000, 0, 5, Endian::Big).unwrap();
    for i in 0..2 {
        for j in 0..2 {
            w.write_trace(10 + i, 20 + j, i as f64, j as f64, &[0.0; 4])
                .unwrap();
        }
    }
    w.finish().unwrap();
    let seed = std::fs::read(&small.0).unwrap();
    let mut b = seed[..3600].to_vec();
    put_u16(&mut b, 3221, 65535, Endian::Big);
    b[3268..3272].copy_from_slice(&(ns as u32).to_be_bytes());
    b[3500] = 2;
    b[3501] = 0;
    for k in 0..4usize {
        let mut h = seed[3600 + k * (240 + 16)..][..240].to_vec();
        put_u16(&mut h, 115, 65535, Endian::Big);
        b.extend_from_slice(&h);
        for s in 0..ns {
            b.extend_from_slice(&((k * 100_000 + s) as f32).to_be_bytes());
        }
    }
    std::fs::write(&t.0, &b).unwrap();
    let v = open(&t.0, &SegyOptions::default()).unwrap();
    assert_eq!(v.dims(), [2, 2, ns as u64]);
    let mut out = vec![0.0f32; ns];
    let tr = v.trace_at(1, 1).unwrap();
    v.read_trace(tr, &mut out).unwrap();
    assert_eq!(out[ns - 1], (3 * 100_000 + ns - 1) as f32);
}

#[test]
fn three_byte_integers_decode_from_literal_bytes() {
    // Bytes written by hand, not by this crate's writer: a byte-order mistake made alike in
    // the writer and the reader would pass the round trip above.
    use super::samples::{decode_strided, Format};
    let big: [u8; 12] = [
        0x80, 0x00, 0x01, 0xFF, 0xFF, 0xFF, 0x01, 0x02, 0x03, 0x7F, 0xFF, 0xFF,
    ];
    let little: [u8; 12] = [
        0x01, 0x00, 0x80, 0xFF, 0xFF, 0xFF, 0x03, 0x02, 0x01, 0xFF, 0xFF, 0x7F,
    ];
    for (fmt, want) in [
        (Format::I24, [-8_388_607.0f32, -1.0, 66_051.0, 8_388_607.0]),
        (
            Format::U24,
            [8_388_609.0f32, 16_777_215.0, 66_051.0, 8_388_607.0],
        ),
    ] {
        for (endian, bytes) in [(Endian::Big, &big), (Endian::Little, &little)] {
            // Every other element, from the second: the stride and start are honoured too.
            let mut out = [f32::NAN; 9];
            decode_strided(fmt, endian, bytes, &mut out, 1, 2);
            let got: Vec<f32> = out.iter().skip(1).step_by(2).copied().collect();
            assert_eq!(got, want, "{fmt:?} {endian:?}");
            assert!(out.iter().step_by(2).all(|v| v.is_nan()), "{out:?}");
        }
    }
}
