//! Writing rendered images: 8-bit sRGB PNG (flattened over a background) and 32-bit float
//! OpenEXR (premultiplied linear RGBA, as rendered).
//!
//! Images arrive as premultiplied linear RGBA, one `[f32; 4]` per pixel, row 0 at the top.
//! Both writers go through a hidden temporary file beside the target (`.NAME.tmpPID`) that
//! is synced and renamed into place, and removed on any error, so a failed write never
//! leaves a half-written image under the final name (nor a stray temporary).

use anyhow::{Context, Result};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use strata_common::wall::WallGeometry;
pub use strata_common::wall::{tile_files, TileFiles};

/// Writes `rgba` (premultiplied linear RGBA, row 0 at the top) as an 8-bit RGB PNG.
///
/// Each pixel is flattened over `background` (linear RGB): `c + (1 - a) * bg`. Non-finite
/// values become 0, results are clamped to [0, 1] and encoded with the exact piecewise sRGB
/// curve; the file carries an sRGB chunk.
pub fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    rgba: &[[f32; 4]],
    background: [f32; 3],
) -> Result<()> {
    check_size(path, width, height, rgba)?;
    let bytes = flatten_srgb8(rgba, background);
    write_via_temp(path, |file| {
        let mut w = BufWriter::new(file);
        let mut writer = srgb8_png(&mut w, width, height)?;
        writer
            .write_image_data(&bytes)
            .context("cannot write the PNG image data")?;
        writer.finish().context("cannot finish the PNG")?;
        w.flush().context("cannot write the PNG")?;
        Ok(())
    })
}

/// Writes `rgba` (premultiplied linear RGBA, row 0 at the top) as a 32-bit float RGBA
/// OpenEXR file (ZIP-compressed scan lines). Values are written as they are: OpenEXR expects
/// premultiplied colour, and non-finite values are kept.
pub fn write_exr(path: &Path, width: u32, height: u32, rgba: &[[f32; 4]]) -> Result<()> {
    use exr::prelude::*;
    check_size(path, width, height, rgba)?;
    let w = width as usize;
    let channels = SpecificChannels::rgba(|Vec2(x, y): Vec2<usize>| {
        let p = rgba[y * w + x];
        (p[0], p[1], p[2], p[3])
    });
    let image = Image::from_encoded_channels(
        (width as usize, height as usize),
        Encoding::SMALL_LOSSLESS,
        channels,
    );
    write_via_temp(path, |file| {
        image
            .write()
            .to_unbuffered(file)
            .map_err(|e| anyhow::anyhow!("cannot write the EXR image: {e}"))
    })
}

/// Maps NaN and infinities to 0.
fn finite_or_zero(v: f32) -> f32 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

/// Premultiplied linear RGBA → 8-bit sRGB RGB, flattened over `background` (see
/// [`write_png`]), rows in parallel: the encoding sits between every frame of a sequence and
/// its file, so it is on the frame's critical path.
fn flatten_srgb8(rgba: &[[f32; 4]], background: [f32; 3]) -> Vec<u8> {
    use rayon::prelude::*;
    let bg = background.map(finite_or_zero);
    let table = srgb8_thresholds();
    let mut bytes = vec![0u8; rgba.len() * 3];
    const CHUNK: usize = 4096;
    bytes
        .par_chunks_mut(CHUNK * 3)
        .zip(rgba.par_chunks(CHUNK))
        .for_each(|(out, px)| {
            for (o, p) in out.chunks_exact_mut(3).zip(px) {
                let a = finite_or_zero(p[3]).clamp(0.0, 1.0);
                for ((o, c), b) in o.iter_mut().zip(&p[..3]).zip(bg) {
                    let flat = finite_or_zero(finite_or_zero(*c) + (1.0 - a) * b);
                    *o = srgb8_from(table, flat);
                }
            }
        });
    bytes
}

/// The 8-bit sRGB code of `linear`, from the table of [`srgb8_thresholds`]: the number of
/// thresholds at or below it. The same code as [`srgb8`] for every `f32`, without a `powf`
/// and without a search: the code where `linear`'s bucket starts, then one step per
/// threshold up to it (at most three).
fn srgb8_from(table: &Srgb8Table, linear: f32) -> u8 {
    let x = linear.clamp(0.0, 1.0);
    if x.is_nan() {
        return 0;
    }
    let mut code = table.start[bucket(x)] as usize;
    while code < 255 && table.thresholds[code] <= x {
        code += 1;
    }
    code as u8
}

/// Mantissa bits of a bucket of [`Srgb8Table::start`]: 32 buckets per octave.
const BUCKET_BITS: u32 = 5;
/// The exponent field of 2^-14: every `f32` below it has code 0 (the first threshold is
/// about 1.5e-4, 2^-12.7).
const FIRST_EXPONENT: u32 = 113;
/// Buckets: one below 2^-14, then 32 per octave up to 1.0, which has one of its own.
const BUCKETS: usize = 2 + ((127 - FIRST_EXPONENT as usize) << BUCKET_BITS);

/// The bucket of `x` in [0, 1]: 0 below 2^-14, else by exponent and the top mantissa bits
/// (−0 is 0).
fn bucket(x: f32) -> usize {
    let b = (x.to_bits() & 0x7fff_ffff) >> (23 - BUCKET_BITS);
    (b + 1).saturating_sub(FIRST_EXPONENT << BUCKET_BITS) as usize
}

/// The smallest `f32` of bucket `i` ≥ 1.
fn bucket_start(i: usize) -> f32 {
    f32::from_bits((i as u32 - 1 + (FIRST_EXPONENT << BUCKET_BITS)) << (23 - BUCKET_BITS))
}

/// The thresholds of the 255 codes above 0, and the code at the start of each bucket.
struct Srgb8Table {
    /// `thresholds[k − 1]` is the smallest `f32` whose [`srgb8`] code is at least `k`.
    thresholds: [f32; 255],
    /// The code of each bucket's smallest `f32` ([`bucket`]).
    start: [u8; BUCKETS],
}

/// The table of [`srgb8_from`]. `thresholds[k − 1]` is the smallest `f32` whose [`srgb8`]
/// code is at least `k` (k = 1 … 255). [`srgb8`] is non-decreasing in its argument and
/// non-negative finite `f32`s are ordered like their bit patterns, so each threshold is
/// found by bisection over the bits; the table then reproduces the exact curve bit for bit.
fn srgb8_thresholds() -> &'static Srgb8Table {
    static TABLE: std::sync::OnceLock<Srgb8Table> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        let mut t = [0f32; 255];
        for (i, t) in t.iter_mut().enumerate() {
            let k = i as u8 + 1;
            // srgb8(lo) < k <= srgb8(hi), over the bits of [0, 1].
            let (mut lo, mut hi) = (0u32, 1f32.to_bits());
            while hi - lo > 1 {
                let mid = lo + (hi - lo) / 2;
                if srgb8(f32::from_bits(mid)) >= k {
                    hi = mid;
                } else {
                    lo = mid;
                }
            }
            *t = f32::from_bits(hi);
        }
        let mut start = [0u8; BUCKETS];
        for (i, s) in start.iter_mut().enumerate().skip(1) {
            *s = t.partition_point(|&th| th <= bucket_start(i)) as u8;
        }
        Srgb8Table {
            thresholds: t,
            start,
        }
    })
}

/// Linear [0, 1] (clamped) → 8-bit sRGB with the exact piecewise curve.
fn srgb8(linear: f32) -> u8 {
    let c = f64::from(linear.clamp(0.0, 1.0));
    let s = if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0).round().clamp(0.0, 255.0) as u8
}

/// Writes tiles `first..first + n` of a wall from their rows of the stacked image
/// (`pixels` holds `n · tile_w · tile_h` pixels, tile `first` first), each to its files.
pub fn write_tiles(
    wall: &WallGeometry,
    first: u32,
    pixels: &[[f32; 4]],
    files: &[TileFiles],
    background: [f32; 3],
) -> Result<()> {
    let n = wall.tile_pixels() as usize;
    anyhow::ensure!(
        n > 0 && pixels.len().is_multiple_of(n),
        "{} pixels are not whole tiles of {}x{}",
        pixels.len(),
        wall.tile_w,
        wall.tile_h
    );
    for (i, tile) in pixels.chunks_exact(n).enumerate() {
        let t = first as usize + i;
        let f = files
            .get(t)
            .with_context(|| format!("no output named for tile {t}"))?;
        write_png(&f.png, wall.tile_w, wall.tile_h, tile, background)?;
        if let Some(e) = &f.exr {
            write_exr(e, wall.tile_w, wall.tile_h, tile)?;
        }
    }
    Ok(())
}

/// Colour of the mullions in the preview mosaic (8-bit sRGB).
pub const MULLION_RGB: [u8; 3] = [24, 24, 24];

/// Writes the preview mosaic of a wall to `path`: the tile PNGs (`files`, row-major) placed
/// where they hang, with the mullions drawn in [`MULLION_RGB`]. It is assembled from the
/// tile files one row of tiles at a time, so it never holds more than one row of tiles
/// and the output's rows. A missing or wrong-sized tile is an error naming the file.
pub fn write_preview(wall: &WallGeometry, files: &[TileFiles], path: &Path) -> Result<()> {
    anyhow::ensure!(
        files.len() == wall.tiles() as usize,
        "{} tile files for {} tiles",
        files.len(),
        wall.tiles()
    );
    let (pw, ph) = wall.plane_size();
    let (tw, th) = (wall.tile_w as usize, wall.tile_h as usize);
    write_via_temp(path, |file| {
        let mut w = BufWriter::new(file);
        let mut writer = srgb8_png(&mut w, pw, ph)?;
        {
            let mut stream = writer
                .stream_writer()
                .context("cannot start the PNG data")?;
            let mullion_row: Vec<u8> = MULLION_RGB.repeat(pw as usize);
            for r in 0..wall.rows {
                if r > 0 {
                    for _ in 0..wall.mullion_y {
                        stream.write_all(&mullion_row)?;
                    }
                }
                let tiles: Vec<Vec<u8>> = (0..wall.cols)
                    .map(|c| read_rgb8(&files[(r * wall.cols + c) as usize].png, wall))
                    .collect::<Result<_>>()?;
                let mut row = Vec::with_capacity(pw as usize * 3);
                for y in 0..th {
                    row.clear();
                    for (c, t) in tiles.iter().enumerate() {
                        if c > 0 {
                            row.extend(MULLION_RGB.repeat(wall.mullion_x as usize));
                        }
                        row.extend_from_slice(&t[y * tw * 3..(y + 1) * tw * 3]);
                    }
                    stream.write_all(&row)?;
                }
            }
            stream.finish().context("cannot finish the PNG data")?;
        }
        writer.finish().context("cannot finish the PNG")?;
        w.flush().context("cannot write the PNG")?;
        Ok(())
    })
}

/// Reads a tile PNG written by [`write_tiles`] as 8-bit RGB rows, checking its size.
fn read_rgb8(path: &Path, wall: &WallGeometry) -> Result<Vec<u8>> {
    let f =
        File::open(path).with_context(|| format!("{}: cannot open the tile", path.display()))?;
    let mut reader = png::Decoder::new(std::io::BufReader::new(f))
        .read_info()
        .with_context(|| format!("{}: not a PNG", path.display()))?;
    let info = reader.info();
    anyhow::ensure!(
        (info.width, info.height) == (wall.tile_w, wall.tile_h)
            && info.color_type == png::ColorType::Rgb
            && info.bit_depth == png::BitDepth::Eight,
        "{}: expected an 8-bit RGB tile of {}x{}, found {:?} {:?} {}x{}",
        path.display(),
        wall.tile_w,
        wall.tile_h,
        info.bit_depth,
        info.color_type,
        info.width,
        info.height
    );
    let mut buf = vec![0; reader.output_buffer_size().context("tile too large")?];
    reader
        .next_frame(&mut buf)
        .with_context(|| format!("{}: cannot decode the tile", path.display()))?;
    buf.truncate(wall.tile_pixels() as usize * 3);
    Ok(buf)
}

/// An 8-bit sRGB RGB PNG of `width × height`, its header written.
fn srgb8_png<W: Write>(out: W, width: u32, height: u32) -> Result<png::Writer<W>> {
    let mut enc = png::Encoder::new(out, width, height);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    // fdeflate's fast mode: 7x faster than the default level on rendered frames, and no
    // larger (414 against 428 kB on a demo frame).
    enc.set_compression(png::Compression::Fast);
    enc.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
    enc.write_header().context("cannot write the PNG header")
}

fn check_size(path: &Path, width: u32, height: u32, rgba: &[[f32; 4]]) -> Result<()> {
    anyhow::ensure!(
        width > 0 && height > 0,
        "{}: cannot write an empty image ({width}x{height})",
        path.display()
    );
    let n = (width as usize).checked_mul(height as usize);
    anyhow::ensure!(
        n == Some(rgba.len()),
        "{}: the image is {width}x{height} but {} pixels were given",
        path.display(),
        rgba.len()
    );
    Ok(())
}

/// The hidden temporary name beside `path`: `.NAME.tmpPID` ([`strata_common::temp_name`]; long
/// names are cut and numbered).
fn temp_path(path: &Path) -> Result<PathBuf> {
    strata_common::temp_name::temp_sibling(path, std::process::id())
        .with_context(|| format!("{}: not a file name", path.display()))
}

/// Creates the temporary file, lets `write` fill it, syncs it and renames it to `path`;
/// removes the temporary on any error.
fn write_via_temp(path: &Path, write: impl FnOnce(&mut File) -> Result<()>) -> Result<()> {
    let tmp = temp_path(path)?;
    let mut file = File::create(&tmp).with_context(|| {
        format!(
            "{}: cannot create it (through the temporary file {})",
            path.display(),
            tmp.display()
        )
    })?;
    let result = write(&mut file)
        .and_then(|()| file.sync_all().context("cannot sync"))
        .with_context(|| format!("{}: cannot write", path.display()))
        .and_then(|()| {
            drop(file);
            std::fs::rename(&tmp, path)
                .with_context(|| format!("cannot rename {} to {}", tmp.display(), path.display()))
        });
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read_png(path: &Path) -> (u32, u32, png::ColorType, Vec<u8>) {
        let file = std::io::BufReader::new(File::open(path).unwrap());
        let mut reader = png::Decoder::new(file).read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        buf.truncate(info.buffer_size());
        (info.width, info.height, info.color_type, buf)
    }

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    /// The threshold table gives the exact curve's code: on every 61st `f32` of [0, 1], on
    /// the 33 around each threshold, and outside [0, 1]. A threshold one ulp off fails it.
    #[test]
    fn srgb8_table_equals_the_exact_curve() {
        let t = srgb8_thresholds();
        let one = 1f32.to_bits();
        let mut bits: Vec<u32> = (0..=one).step_by(61).collect();
        for th in &t.thresholds {
            let b = th.to_bits();
            bits.extend(b.saturating_sub(16)..=(b + 16).min(one));
        }
        for b in bits {
            let x = f32::from_bits(b);
            assert_eq!(srgb8_from(t, x), srgb8(x), "at {x:e} (bits {b:#x})");
        }
        for x in [-0.0, -1e-30, -1.0, 1.0 + f32::EPSILON, 7.0, f32::INFINITY] {
            assert_eq!(srgb8_from(t, x), srgb8(x), "at {x:e}");
        }
        assert_eq!(srgb8_from(t, f32::NAN), 0);
        assert!(
            t.thresholds.windows(2).all(|w| w[0] < w[1]),
            "thresholds increase"
        );
        // Each bucket starts at the code of its smallest float and spans at most three.
        for i in 1..BUCKETS {
            let lowest = bucket_start(i);
            assert_eq!(bucket(lowest), i);
            assert_eq!(bucket(lowest.next_down()), i - 1);
            assert_eq!(t.start[i], srgb8(lowest), "bucket {i}");
            let top = if i + 1 < BUCKETS {
                bucket_start(i + 1).next_down()
            } else {
                1.0
            };
            assert!(srgb8(top) - srgb8(lowest) <= 3, "bucket {i}");
        }
        assert_eq!(bucket(0.0), 0);
        assert_eq!(bucket(1.0), BUCKETS - 1);
        assert_eq!(srgb8(bucket_start(1).next_down()), 0);
    }

    #[test]
    fn srgb_curve() {
        assert_eq!(srgb8(0.0), 0);
        assert_eq!(srgb8_from(srgb8_thresholds(), 0.5), 188);
        assert_eq!(srgb8(1.0), 255);
        assert_eq!(srgb8(0.5), 188);
        assert_eq!(srgb8(0.002), 7); // linear segment: 12.92 * 0.002 * 255 = 6.6
        assert_eq!(srgb8(-1.0), 0);
        assert_eq!(srgb8(7.0), 255);
    }

    #[test]
    fn png_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("img.png");
        // 3 x 2, row 0 at the top.
        let rgba = [
            [0.0, 0.0, 0.0, 1.0],
            [1.0, 1.0, 1.0, 1.0],
            [0.5, 0.5, 0.5, 1.0],
            // Premultiplied half-transparent red over a blue background.
            [0.25, 0.0, 0.0, 0.5],
            // Fully transparent: the background itself.
            [0.0, 0.0, 0.0, 0.0],
            // Non-finite and out-of-range values.
            [f32::NAN, f32::INFINITY, 2.0, f32::NAN],
        ];
        write_png(&path, 3, 2, &rgba, [0.0, 0.0, 1.0]).unwrap();
        let (w, h, ct, px) = read_png(&path);
        assert_eq!((w, h, ct), (3, 2, png::ColorType::Rgb));
        assert_eq!(
            px,
            [
                0, 0, 0, //
                255, 255, 255, //
                188, 188, 188, //
                137, 0, 188, // 0.25 -> 137, 0 + 0.5 * 1 -> 188
                0, 0, 255, //
                0, 0, 255, // NaN -> 0, inf -> 0, 2 + (1 - 0) * 1 clamped
            ]
        );
        assert_eq!(names(dir.path()), ["img.png"]);
    }

    #[test]
    fn exr_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("img.exr");
        let (w, h) = (5usize, 3usize);
        let rgba: Vec<[f32; 4]> = (0..w * h)
            .map(|i| {
                let v = i as f32 / 7.0;
                [v, -v, 1e6 * v, 0.5]
            })
            .collect();
        write_exr(&path, w as u32, h as u32, &rgba).unwrap();
        let image = exr::prelude::read_first_rgba_layer_from_file(
            &path,
            |res, _| vec![[0f32; 4]; res.width() * res.height()],
            move |px: &mut Vec<[f32; 4]>, pos, (r, g, b, a): (f32, f32, f32, f32)| {
                px[pos.y() * w + pos.x()] = [r, g, b, a];
            },
        )
        .unwrap();
        assert_eq!(image.layer_data.size.width(), w);
        assert_eq!(image.layer_data.size.height(), h);
        assert_eq!(image.layer_data.channel_data.pixels, rgba);
        assert_eq!(names(dir.path()), ["img.exr"]);
    }

    #[test]
    fn bad_input_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("missing");
        let px = vec![[0.5f32; 4]; 4];
        let e = write_png(&missing.join("a.png"), 2, 2, &px, [0.0; 3]).unwrap_err();
        assert!(format!("{e:#}").contains("a.png"), "{e:#}");
        let e = write_exr(&missing.join("a.exr"), 2, 2, &px).unwrap_err();
        assert!(format!("{e:#}").contains("a.exr"), "{e:#}");
        assert!(!missing.exists());

        let e = write_png(&dir.path().join("b.png"), 3, 2, &px, [0.0; 3]).unwrap_err();
        assert!(e.to_string().contains("3x2 but 4 pixels"), "{e}");
        let e = write_exr(&dir.path().join("b.exr"), 0, 0, &[]).unwrap_err();
        assert!(e.to_string().contains("empty image"), "{e}");
        assert!(names(dir.path()).is_empty());

        // The target is a folder: the rename fails and the temporary is removed.
        std::fs::create_dir(dir.path().join("c.png")).unwrap();
        write_png(&dir.path().join("c.png"), 2, 2, &px, [0.0; 3]).unwrap_err();
        assert_eq!(names(dir.path()), ["c.png"]);
    }

    #[test]
    fn wall_tiles_and_preview_mosaic() {
        let dir = tempfile::tempdir().unwrap();
        let g = WallGeometry {
            cols: 2,
            rows: 2,
            tile_w: 3,
            tile_h: 2,
            mullion_x: 1,
            mullion_y: 2,
        };
        let files = tile_files(&g, &dir.path().join("w.png"), None);
        assert_eq!(files[1].png, dir.path().join("w_c1r0.png"));
        assert_eq!(files[2].png, dir.path().join("w_c0r1.png"));
        // Tile t is solid grey level 0.25·t (opaque).
        let px: Vec<[f32; 4]> = (0..4)
            .flat_map(|t| vec![[0.25 * t as f32, 0.25 * t as f32, 0.25 * t as f32, 1.0]; 6])
            .collect();
        // Tiles 1..4 first, then tile 0: a driver writes only its own.
        write_tiles(&g, 1, &px[6..], &files, [0.0; 3]).unwrap();
        let out = dir.path().join("w.png");
        let e = write_preview(&g, &files, &out).unwrap_err();
        assert!(format!("{e:#}").contains("w_c0r0.png"), "{e:#}");
        assert_eq!(names(dir.path()).len(), 3, "nothing half-written");
        write_tiles(&g, 0, &px[..6], &files, [0.0; 3]).unwrap();
        write_preview(&g, &files, &out).unwrap();
        let (w, h, _, rgb) = read_png(&out);
        assert_eq!((w, h), (7, 6));
        let at = |x: usize, y: usize| rgb[(y * 7 + x) * 3];
        assert_eq!(at(0, 0), 0);
        assert_eq!(at(4, 1), srgb8(0.25));
        assert_eq!(at(3, 0), MULLION_RGB[0]);
        assert_eq!(at(0, 2), MULLION_RGB[0]);
        assert_eq!(at(0, 4), srgb8(0.5));
        assert_eq!(at(6, 5), srgb8(0.75));
        // A tile of the wrong size is named.
        write_png(&files[3].png, 2, 2, &[[0.0; 4]; 4], [0.0; 3]).unwrap();
        let e = write_preview(&g, &files, &out).unwrap_err();
        assert!(format!("{e:#}").contains("w_c1r1.png"), "{e:#}");
    }
}
