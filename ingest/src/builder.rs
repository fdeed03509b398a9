//! Streams a [`GridSource`] into a page store with bounded memory.
//!
//! Level 0 is read from the source in *pencils*: rows of bricks along the source's
//! contiguous axis, limited so one pencil's samples fit the memory budget. Each brick of
//! the pencil is cut out with its border (edge replicas for volumes, holes for horizons),
//! quantized, encoded and appended to the output. Level `l + 1` is then built the same way
//! from level `l` read back out of the file being written, through [`Downsample`], which
//! applies the coarsening filter to each 2×2(×2) group of level-`l` samples (indices past
//! the level's end are clamped, so an odd edge sample is its own neighbour).
//!
//! Memory is bounded by the pencil budget plus a small cache of decoded level-`l` pages,
//! whatever the data set's size. The file is written under a temporary name in the same
//! folder and renamed into place only when complete.

use crate::source::GridSource;
use anyhow::{bail, Context, Result};
use indicatif::ProgressBar;
use rayon::prelude::*;
use std::collections::{HashMap, VecDeque};
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use strata_common::digest::DigestAcc;
use strata_common::filter::CoarsenFilter;
use strata_common::geo::{Affine3, SurveyGrid};
use strata_common::ids::PageId;
use strata_common::pyramid::{Dim, Pyramid};
use strata_common::sample::SampleType;
use strata_common::stats::ValueHistogram;
use strata_common::store::{
    decode_payload, encode_page, encode_page_stored, Compression, DataKind, IndexEntry, Preamble,
    StoreHeader, Units, VerticalDomain, FORMAT_VERSION, PREAMBLE_LEN,
};

/// What to build.
#[derive(Clone, Debug)]
pub struct BuildOptions {
    /// Volume or horizon.
    pub kind: DataKind,
    /// Name recorded in the header.
    pub name: String,
    /// Stored sample type (horizons: F32).
    pub sample_type: SampleType,
    /// No-data sentinel for integer volumes that have missing samples.
    pub no_data: Option<f32>,
    /// Page size per axis including the border (volumes: 32, 64 or 128; horizons: 128).
    pub page_size: u32,
    /// Border per side (1 for trilinear, 2 for gradients).
    pub border: u32,
    /// Coarsening filter.
    pub filter: CoarsenFilter,
    /// Page compression.
    pub compression: Compression,
    /// Sample index to world.
    pub transform: Affine3,
    /// World units.
    pub units: Units,
    /// Whether world z is time or depth, if known.
    pub vertical_domain: Option<VerticalDomain>,
    /// Lateral survey grid, if known.
    pub survey: Option<SurveyGrid>,
    /// Provenance text.
    pub source: String,
    /// Working-memory budget in bytes for pencils and the page cache.
    pub memory_budget: usize,
}

impl BuildOptions {
    /// Defaults for a volume of `sample_type`: 64³ pages, border 1, signed-RMS coarsening for
    /// signed data and the box filter for unsigned data, no compression.
    pub fn volume(name: &str, sample_type: SampleType) -> Self {
        BuildOptions {
            kind: DataKind::Volume,
            name: name.into(),
            sample_type,
            no_data: None,
            page_size: 64,
            border: 1,
            filter: if sample_type.is_signed() {
                CoarsenFilter::SignedRms
            } else {
                CoarsenFilter::Mean
            },
            compression: Compression::None,
            transform: Affine3::IDENTITY,
            units: Units::default(),
            vertical_domain: None,
            survey: None,
            source: String::new(),
            memory_budget: 256 << 20,
        }
    }
    /// Defaults for a horizon: 128² tiles with a border of 2, hole-preserving mean.
    pub fn horizon(name: &str) -> Self {
        BuildOptions {
            kind: DataKind::Horizon,
            page_size: 128,
            border: 2,
            filter: CoarsenFilter::HorizonMean,
            ..Self::volume(name, SampleType::F32)
        }
    }
}

/// What a build did.
#[derive(Clone, Debug, Default)]
pub struct BuildReport {
    /// The header written.
    pub header: Option<StoreHeader>,
    /// Pages in the store.
    pub pages: u64,
    /// Pages stored as constant.
    pub constant_pages: u64,
    /// Pages stored as empty.
    pub empty_pages: u64,
    /// Pages stored compressed.
    pub compressed_pages: u64,
    /// Payload bytes before compression (pages with a payload).
    pub raw_bytes: u64,
    /// Payload bytes on disk.
    pub stored_bytes: u64,
    /// Final file size.
    pub file_bytes: u64,
    /// Level-0 samples read from the source.
    pub source_samples: u64,
    /// Valid level-0 samples whose value was the integer store's no-data sentinel, stored
    /// one unit away from it instead (see [`SampleType::quantize_valid`]) so they are not read
    /// back as holes.
    pub moved_off_no_data: u64,
}

/// Removes the temporary file unless the build completed (on errors and panics here, on
/// signals through [`crate::cleanup`]).
struct TempFile {
    path: PathBuf,
    keep: bool,
    _signals: crate::cleanup::Registered,
}

impl Drop for TempFile {
    fn drop(&mut self) {
        if !self.keep {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

/// The temporary name a build writes to before renaming: hidden, in the same folder, with the pid.
pub fn temp_path_for(out: &Path) -> PathBuf {
    strata_common::temp_name::temp_sibling(out, std::process::id())
        .unwrap_or_else(|| out.with_file_name(format!(".store.tmp{}", std::process::id())))
}

struct Output {
    w: BufWriter<File>,
    offset: u64,
}

/// Builds a page store at `out` from `src`. Nothing appears at `out` unless the build succeeds.
pub fn build_store(
    src: &dyn GridSource,
    out: &Path,
    opts: &BuildOptions,
    progress: &ProgressBar,
) -> Result<BuildReport> {
    let dims = src.dims();
    let dim = match opts.kind {
        DataKind::Volume => Dim::Three,
        DataKind::Horizon => Dim::Two,
    };
    if opts.kind == DataKind::Horizon && opts.sample_type != SampleType::F32 {
        bail!("horizon stores hold f32 heights");
    }
    if let Some(v) = opts
        .no_data
        .filter(|&v| !opts.sample_type.holds_sentinel(v))
    {
        bail!(
            "the no-data value {v} is not a {} value: holes would be written as another value and read back as data",
            opts.sample_type.name()
        );
    }
    // The height filter keeps holes (a coarse node is a hole wherever a child is); the
    // volume filters skip no-data, which on a horizon invents heights across holes, and
    // the height filter on a volume would grow its no-data level by level.
    match (opts.kind, opts.filter) {
        (DataKind::Horizon, f) if f != CoarsenFilter::HorizonMean => bail!(
            "the {} filter is for volumes: a horizon coarsens with horizon-mean (it keeps holes)",
            f.name()
        ),
        (DataKind::Volume, CoarsenFilter::HorizonMean) => bail!(
            "the horizon-mean filter is for horizons: a volume coarsens with mean, signed-rms or max-abs"
        ),
        _ => {}
    }
    if !opts.transform.is_finite() || opts.transform.inverse().is_none() {
        bail!(
            "the index→world transform {:?} is not finite and invertible (a zero or vanishing sample step?)",
            opts.transform.rows
        );
    }
    if opts.kind == DataKind::Volume && ![32, 64, 128].contains(&opts.page_size) {
        bail!("brick size must be 32, 64 or 128, got {}", opts.page_size);
    }
    if !(1..=2).contains(&opts.border) {
        bail!(
            "border must be 1 (trilinear) or 2 (gradients), got {}",
            opts.border
        );
    }
    let pyr = Pyramid::new(dim, dims, opts.page_size, opts.border)
        .with_context(|| format!("cannot lay out {dims:?}"))?;
    let mut header = StoreHeader {
        kind: opts.kind,
        name: opts.name.clone(),
        dims,
        sample_type: opts.sample_type,
        value_range: [f64::NAN, f64::NAN],
        no_data: opts.no_data,
        page_size: opts.page_size,
        border: opts.border,
        levels: pyr.level_count() as u32,
        filter: opts.filter,
        compression: opts.compression,
        transform: opts.transform,
        units: opts.units.clone(),
        survey: opts.survey,
        valid_samples: 0,
        digest: 0,
        source: opts.source.clone(),
        stats: None,
        vertical_domain: opts.vertical_domain,
    };

    // The page index, bounded before anything is written: a layout of more pages than
    // this machine can index fails here, not in an abort.
    let mut entries: Vec<IndexEntry> = Vec::new();
    entries
        .try_reserve_exact(pyr.total_pages() as usize)
        .map_err(|_| {
            anyhow::anyhow!(
                "{dims:?} samples make {} pages, more than this machine can index",
                pyr.total_pages()
            )
        })?;
    let path = temp_path_for(out);
    let tmp = TempFile {
        _signals: crate::cleanup::register(&path),
        path,
        keep: false,
    };
    let file = File::create(&tmp.path)
        .with_context(|| format!("{}: cannot create", tmp.path.display()))?;
    let mut o = Output {
        w: BufWriter::with_capacity(8 << 20, file),
        offset: PREAMBLE_LEN,
    };
    o.w.write_all(&[0u8; PREAMBLE_LEN as usize])
        .with_context(|| format!("{}: cannot write", tmp.path.display()))?;

    progress.set_length(pyr.total_pages());
    let mut report = BuildReport {
        pages: pyr.total_pages(),
        ..Default::default()
    };
    let mut stats = Level0Stats {
        hist: Some(Box::default()),
        ..Level0Stats::default()
    };

    // Level 0 from the source.
    let mut prev = build_level(
        src,
        0,
        &pyr,
        &header,
        &mut o,
        &mut entries,
        Some(&mut stats),
        None,
        opts,
        progress,
        &mut report,
    )
    .with_context(|| format!("while building level 0 of {}", out.display()))?;
    if opts.sample_type != SampleType::F32
        && opts.no_data.is_none()
        && stats.acc.count() != stats.valid
    {
        bail!(
            "the source has {} no-data samples but the {} store has no no-data sentinel",
            stats.acc.count() - stats.valid,
            opts.sample_type.name()
        );
    }
    header.valid_samples = stats.valid;
    header.digest = stats.acc.finish(dims);
    if stats.valid > 0 {
        header.value_range = [stats.min as f64, stats.max as f64];
    }
    header.stats = stats.hist.as_deref().and_then(ValueHistogram::stats);
    report.source_samples = stats.acc.count();
    report.moved_off_no_data = stats.moved_off_no_data;

    // Coarser levels from the level below, read back from the file being written.
    for l in 1..pyr.level_count() {
        o.w.flush()
            .with_context(|| format!("{}: cannot write", tmp.path.display()))?;
        let reader = File::open(&tmp.path)
            .with_context(|| format!("{}: cannot reopen", tmp.path.display()))?;
        let fine = LevelSource::new(
            reader,
            &header,
            &pyr,
            l - 1,
            &entries,
            opts.memory_budget / 4,
        );
        let coarse = Downsample {
            fine: &fine,
            filter: opts.filter,
            dims: pyr.level(l).dims,
            dim,
        };
        prev = build_level(
            &coarse,
            l,
            &pyr,
            &header,
            &mut o,
            &mut entries,
            None,
            Some(&prev),
            opts,
            progress,
            &mut report,
        )
        .with_context(|| format!("while building level {l} of {}", out.display()))?;
    }

    // Header and index after the data; then the preamble that points at them.
    let hb = bincode::serde::encode_to_vec(&header, bincode::config::standard())?;
    let header_offset = o.offset;
    o.w.write_all(&hb)
        .with_context(|| format!("{}: cannot write", tmp.path.display()))?;
    let index_offset = header_offset + hb.len() as u64;
    entries.sort_unstable_by_key(|e| e.id);
    let ib: &[u8] = bytemuck::cast_slice(&entries);
    o.w.write_all(ib)
        .with_context(|| format!("{}: cannot write", tmp.path.display()))?;
    let pre = Preamble {
        version: FORMAT_VERSION,
        header_offset,
        header_len: hb.len() as u64,
        index_offset,
        index_count: entries.len() as u64,
        header_crc: crc32c::crc32c(&hb),
        index_crc: crc32c::crc32c(ib),
    };
    let mut file =
        o.w.into_inner()
            .map_err(|e| e.into_error())
            .with_context(|| format!("{}: cannot write", tmp.path.display()))?;
    file.seek(SeekFrom::Start(0))
        .with_context(|| format!("{}: cannot write", tmp.path.display()))?;
    file.write_all(&pre.encode())
        .with_context(|| format!("{}: cannot write", tmp.path.display()))?;
    file.sync_all()
        .with_context(|| format!("{}: sync failed", tmp.path.display()))?;
    report.file_bytes = index_offset + ib.len() as u64;
    drop(file);
    std::fs::rename(&tmp.path, out)
        .with_context(|| format!("cannot rename {} to {}", tmp.path.display(), out.display()))?;
    let mut tmp = tmp;
    tmp.keep = true;
    report.header = Some(header);
    Ok(report)
}

#[derive(Default)]
struct Level0Stats {
    acc: DigestAcc,
    valid: u64,
    min: f32,
    max: f32,
    /// Valid source samples that would have been stored as the no-data sentinel.
    moved_off_no_data: u64,
    /// A page's valid core values, for the data set's histogram.
    values: Vec<f32>,
    /// The data set's: every page's values counted (mean, RMS, percentiles).
    hist: Option<Box<ValueHistogram>>,
}

/// Min/max of each page of the level just built, for conservative parent bounds.
type LevelBounds = HashMap<PageId, (f32, f32)>;

#[allow(clippy::too_many_arguments)]
fn build_level(
    src: &dyn GridSource,
    level: usize,
    pyr: &Pyramid,
    header: &StoreHeader,
    o: &mut Output,
    entries: &mut Vec<IndexEntry>,
    mut stats: Option<&mut Level0Stats>,
    children: Option<&LevelBounds>,
    opts: &BuildOptions,
    progress: &ProgressBar,
    report: &mut BuildReport,
) -> Result<LevelBounds> {
    let lev = *pyr.level(level);
    let (pd, core, border) = (pyr.page_dims(), pyr.core3(), pyr.border3());
    let a = src.contiguous_axis();
    let (b, c) = match a {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    };
    // Bricks per pencil chunk: level 0 reads the source directly; coarse levels read 8× as
    // many fine samples through the downsampler.
    let budget_samples = (opts.memory_budget / 4 / 4 / if level == 0 { 1 } else { 8 }).max(1);
    let per_brick = core[a] as usize * pd[b] as usize * pd[c] as usize;
    let chunk = (budget_samples / per_brick).clamp(1, lev.bricks[a] as usize) as u32;
    let mut bounds = LevelBounds::new();

    // The pencils of this level, in write order.
    let mut pencils: Vec<Pencil> = Vec::new();
    for jc in 0..lev.bricks[c] {
        for jb in 0..lev.bricks[b] {
            let mut k0 = 0;
            while k0 < lev.bricks[a] {
                let k1 = (k0 + chunk).min(lev.bricks[a]);
                let mut r0 = [0u32; 3];
                let mut r1 = [0u32; 3];
                (r0[a], r1[a]) = (k0, k1);
                (r0[b], r1[b]) = (jb, jb + 1);
                (r0[c], r1[c]) = (jc, jc + 1);
                let mut blo = [0u64; 3];
                let mut bsz = [0u64; 3];
                for ax in 0..3 {
                    let lo = (r0[ax] as i64 * core[ax] as i64 - border[ax] as i64).max(0) as u64;
                    let hi = ((r1[ax] as i64 * core[ax] as i64 + border[ax] as i64) as u64)
                        .min(lev.dims[ax]);
                    blo[ax] = lo;
                    bsz[ax] = hi - lo;
                }
                let bricks = (k0..k1)
                    .map(|k| {
                        let mut br = [0u32; 3];
                        (br[a], br[b], br[c]) = (k, jb, jc);
                        br
                    })
                    .collect();
                pencils.push(Pencil { blo, bsz, bricks });
                k0 = k1;
            }
        }
    }

    // Three stages that overlap: a reader thread fills the next pencil while rayon encodes
    // this one and a writer thread appends the previous one's pages. Channels of depth 1
    // keep at most three pencils in memory.
    let (read_tx, read_rx) = std::sync::mpsc::sync_channel::<(usize, Vec<f32>)>(1);
    let (write_tx, write_rx) = std::sync::mpsc::sync_channel::<Vec<Vec<u8>>>(1);
    let Output { w, offset } = o;
    std::thread::scope(|scope| -> Result<()> {
        let pencils = &pencils;
        let reader = scope.spawn(move || -> Result<()> {
            for (i, p) in pencils.iter().enumerate() {
                let mut buf = vec![0f32; (p.bsz[0] * p.bsz[1] * p.bsz[2]) as usize];
                src.read_box(p.blo, p.bsz, &mut buf)?;
                if read_tx.send((i, buf)).is_err() {
                    break; // the encoder stopped on an error of its own
                }
            }
            Ok(())
        });
        let writer = scope.spawn(move || -> Result<()> {
            for pages in write_rx {
                for bytes in pages {
                    w.write_all(&bytes)?;
                }
            }
            Ok(())
        });
        let encode = || -> Result<()> {
            for (i, buf) in read_rx {
                let p = &pencils[i];
                let encoded: Vec<(IndexEntry, Vec<u8>, Option<Level0Stats>)> = p
                    .bricks
                    .par_iter()
                    .map(|&br| {
                        let page = cut_page(pyr, level, br, &buf, p.blo, p.bsz, header);
                        let id = pyr.id(level, br);
                        let st = (level == 0).then(|| {
                            let mut st = core_stats(pyr, br, &page, lev.dims);
                            st.moved_off_no_data =
                                moved_off_no_data(pyr, br, &buf, p.blo, p.bsz, header);
                            st
                        });
                        let (mut e, mut bytes) = encode_page(header, id, &page);
                        if let Some(ch) = children {
                            // A coarse page's bounds cover its children's, so empty-space skipping and
                            // min-max traversal stay conservative across levels.
                            let (own_min, own_max) = (e.min, e.max);
                            for child in pyr.children(level, br) {
                                if let Some(&(mn, mx)) = ch.get(&pyr.id(level - 1, child)) {
                                    if !mn.is_nan() {
                                        e.min = if e.min.is_nan() { mn } else { e.min.min(mn) };
                                        e.max = if e.max.is_nan() { mx } else { e.max.max(mx) };
                                    }
                                }
                            }
                            // A constant page is read back as its entry's min: one whose bounds
                            // widened keeps its samples instead (its children vary where it
                            // does not: a filter's mean or RMS of a checkerboard, u8 rounding).
                            if e.flags & strata_common::store::PAGE_CONSTANT != 0
                                && (e.min != own_min || e.max != own_max)
                            {
                                let (min, max) = (e.min, e.max);
                                (e, bytes) = encode_page_stored(header, id, &page);
                                (e.min, e.max) = (min, max);
                            }
                        }
                        (e, bytes, st)
                    })
                    .collect();
                drop(buf);
                let mut out = Vec::with_capacity(encoded.len());
                for (mut e, bytes, st) in encoded {
                    if e.has_payload() {
                        e.offset = *offset;
                        *offset += bytes.len() as u64;
                        report.raw_bytes += header.page_raw_len() as u64;
                        report.stored_bytes += bytes.len() as u64;
                        if e.flags & strata_common::store::PAGE_COMPRESSED != 0 {
                            report.compressed_pages += 1;
                        }
                        out.push(bytes);
                    } else if e.flags & strata_common::store::PAGE_EMPTY != 0 {
                        report.empty_pages += 1;
                    } else {
                        report.constant_pages += 1;
                    }
                    if let (Some(s), Some(t)) = (stats.as_deref_mut(), st) {
                        if t.valid > 0 {
                            if s.valid == 0 {
                                (s.min, s.max) = (t.min, t.max);
                            } else {
                                s.min = s.min.min(t.min);
                                s.max = s.max.max(t.max);
                            }
                        }
                        s.valid += t.valid;
                        s.moved_off_no_data += t.moved_off_no_data;
                        s.acc = s.acc.combine(t.acc);
                        if let Some(h) = s.hist.as_deref_mut() {
                            for &v in &t.values {
                                h.add(v);
                            }
                        }
                    }
                    bounds.insert(e.id, (e.min, e.max));
                    entries.push(e);
                    progress.inc(1);
                }
                if write_tx.send(out).is_err() {
                    break; // the writer failed; its error is reported below
                }
            }
            Ok(())
        };
        let encoded = encode();
        drop(write_tx);
        let written = writer.join().expect("writer thread panicked");
        let read = reader.join().expect("reader thread panicked");
        // The first failure in pipeline order is the cause; later ones are consequences.
        read?;
        encoded?;
        written
    })?;
    Ok(bounds)
}

/// One row of bricks along the source's contiguous axis and the sample box it needs.
struct Pencil {
    blo: [u64; 3],
    bsz: [u64; 3],
    bricks: Vec<[u32; 3]>,
}

/// Cuts one page (border included) out of a pencil buffer.
fn cut_page(
    pyr: &Pyramid,
    level: usize,
    br: [u32; 3],
    buf: &[f32],
    blo: [u64; 3],
    bsz: [u64; 3],
    h: &StoreHeader,
) -> Vec<f32> {
    let pd = pyr.page_dims();
    let dims = pyr.level(level).dims;
    let origin = pyr.page_origin(br);
    let horizon = h.kind == DataKind::Horizon;
    // Per axis: page-local coordinate → index into the pencil buffer, or None beyond the edge
    // of a horizon (no surface there). Volumes replicate the edge sample (clamp-to-edge).
    let map = |ax: usize| -> Vec<Option<usize>> {
        (0..pd[ax] as i64)
            .map(|p| {
                let g = origin[ax] + p;
                if horizon && (g < 0 || g >= dims[ax] as i64) {
                    None
                } else {
                    Some((g.clamp(0, dims[ax] as i64 - 1) as u64 - blo[ax]) as usize)
                }
            })
            .collect()
    };
    let (mx, my, mz) = (map(0), map(1), map(2));
    let mut page = vec![f32::NAN; pyr.page_samples()];
    let q = |v: f32| h.sample_type.quantize_valid(v, h.no_data);
    let mut i = 0;
    for z in &mz {
        for y in &my {
            match (z, y) {
                (Some(z), Some(y)) => {
                    let row = (*z * bsz[1] as usize + *y) * bsz[0] as usize;
                    for x in &mx {
                        page[i] = x.map_or(f32::NAN, |x| q(buf[row + x]));
                        i += 1;
                    }
                }
                _ => i += mx.len(),
            }
        }
    }
    page
}

/// How many valid source samples of the level-0 page `br` owns (its core) quantize to the
/// store's no-data sentinel, and so are stored one unit away from it.
fn moved_off_no_data(
    pyr: &Pyramid,
    br: [u32; 3],
    buf: &[f32],
    blo: [u64; 3],
    bsz: [u64; 3],
    h: &StoreHeader,
) -> u64 {
    let Some(nd) = h.no_data.filter(|_| h.sample_type != SampleType::F32) else {
        return 0;
    };
    if h.kind != DataKind::Volume {
        return 0;
    }
    let r = pyr.core_range(0, br);
    let mut n = 0;
    for z in r[2].0..r[2].1 {
        for y in r[1].0..r[1].1 {
            let row = ((z - blo[2]) * bsz[1] + (y - blo[1])) * bsz[0];
            for x in r[0].0..r[0].1 {
                let v = buf[(row + x - blo[0]) as usize];
                if !v.is_nan() && h.sample_type.quantize(v) == nd {
                    n += 1;
                }
            }
        }
    }
    n
}

/// Digest terms and range of the samples a level-0 page owns (its core inside the data set).
fn core_stats(pyr: &Pyramid, br: [u32; 3], page: &[f32], dims: [u64; 3]) -> Level0Stats {
    let pd = pyr.page_dims();
    let origin = pyr.page_origin(br);
    let r = pyr.core_range(0, br);
    let mut s = Level0Stats {
        min: f32::INFINITY,
        max: f32::NEG_INFINITY,
        ..Default::default()
    };
    for z in r[2].0..r[2].1 {
        for y in r[1].0..r[1].1 {
            let prow = (((z as i64 - origin[2]) as usize) * pd[1] as usize
                + (y as i64 - origin[1]) as usize)
                * pd[0] as usize;
            let grow = (z * dims[1] + y) * dims[0];
            for x in r[0].0..r[0].1 {
                let v = page[prow + (x as i64 - origin[0]) as usize];
                s.acc.add(grow + x, v);
                if !v.is_nan() {
                    s.valid += 1;
                    s.min = s.min.min(v);
                    s.max = s.max.max(v);
                    s.values.push(v);
                }
            }
        }
    }
    s
}

/// One level of a store being written (or already written), readable as a grid.
pub struct LevelSource {
    file: File,
    header: StoreHeader,
    pyr: Pyramid,
    level: usize,
    entries: HashMap<PageId, IndexEntry>,
    cache: Mutex<(HashMap<PageId, Arc<Vec<f32>>>, VecDeque<PageId>)>,
    cache_pages: usize,
}

impl LevelSource {
    /// Reads `level` of the store in `file` whose pages are listed in `entries`.
    pub fn new(
        file: File,
        header: &StoreHeader,
        pyr: &Pyramid,
        level: usize,
        entries: &[IndexEntry],
        cache_bytes: usize,
    ) -> Self {
        let entries = entries
            .iter()
            .filter(|e| e.id.level() as usize == level)
            .map(|e| (e.id, *e))
            .collect();
        LevelSource {
            file,
            header: header.clone(),
            pyr: pyr.clone(),
            level,
            entries,
            cache: Mutex::new((HashMap::new(), VecDeque::new())),
            cache_pages: (cache_bytes / (pyr.page_samples() * 4)).max(8),
        }
    }

    fn page(&self, id: PageId) -> Result<Arc<Vec<f32>>> {
        if let Some(p) = self.cache.lock().unwrap().0.get(&id) {
            return Ok(p.clone());
        }
        let e = self
            .entries
            .get(&id)
            .with_context(|| format!("{id} missing while building the next level"))?;
        let mut stored = vec![0u8; e.stored_len as usize];
        if e.has_payload() {
            self.file.read_exact_at(&mut stored, e.offset)?;
        }
        let mut out = vec![0f32; self.pyr.page_samples()];
        decode_payload(&self.header, e, &stored, &mut out)
            .map_err(|m| anyhow::anyhow!("{id}: expected {m}"))?;
        let p = Arc::new(out);
        let mut c = self.cache.lock().unwrap();
        if c.0.insert(id, p.clone()).is_none() {
            c.1.push_back(id);
            while c.1.len() > self.cache_pages {
                let old = c.1.pop_front().unwrap();
                c.0.remove(&old);
            }
        }
        Ok(p)
    }
}

impl GridSource for LevelSource {
    fn dims(&self) -> [u64; 3] {
        self.pyr.level(self.level).dims
    }
    fn contiguous_axis(&self) -> usize {
        0
    }
    fn read_box(&self, lo: [u64; 3], size: [u64; 3], out: &mut [f32]) -> Result<()> {
        let core = self.pyr.core3();
        let b0 = [0, 1, 2].map(|a| (lo[a] / core[a] as u64) as u32);
        let b1 = [0, 1, 2].map(|a| ((lo[a] + size[a] - 1) / core[a] as u64) as u32);
        let mut bricks = Vec::new();
        for z in b0[2]..=b1[2] {
            for y in b0[1]..=b1[1] {
                for x in b0[0]..=b1[0] {
                    bricks.push([x, y, z]);
                }
            }
        }
        let pages: Vec<Result<Arc<Vec<f32>>>> = bricks
            .par_iter()
            .map(|&br| self.page(self.pyr.id(self.level, br)))
            .collect();
        let pd = self.pyr.page_dims().map(|v| v as usize);
        for (br, page) in bricks.iter().zip(pages) {
            let page = page?;
            let r = self.pyr.core_range(self.level, *br);
            let origin = self.pyr.page_origin(*br);
            let s = [0, 1, 2].map(|a| r[a].0.max(lo[a]));
            let e = [0, 1, 2].map(|a| r[a].1.min(lo[a] + size[a]));
            for z in s[2]..e[2] {
                for y in s[1]..e[1] {
                    let pz = (z as i64 - origin[2]) as usize;
                    let py = (y as i64 - origin[1]) as usize;
                    let px0 = (s[0] as i64 - origin[0]) as usize;
                    let n = (e[0] - s[0]) as usize;
                    let src = &page[(pz * pd[1] + py) * pd[0] + px0..][..n];
                    let o =
                        (((z - lo[2]) * size[1] + (y - lo[1])) * size[0] + (s[0] - lo[0])) as usize;
                    out[o..o + n].copy_from_slice(src);
                }
            }
        }
        Ok(())
    }
}

/// Level `l + 1` as a grid: each sample is the coarsening filter over the 2×2(×2) samples of
/// level `l` below it, with indices clamped at the level's end.
pub struct Downsample<'a> {
    /// The finer level.
    pub fine: &'a dyn GridSource,
    /// The filter.
    pub filter: CoarsenFilter,
    /// Coarse dimensions (`ceil(fine / 2)`, z stays 1 for quadtrees).
    pub dims: [u64; 3],
    /// Octree or quadtree.
    pub dim: Dim,
}

impl GridSource for Downsample<'_> {
    fn dims(&self) -> [u64; 3] {
        self.dims
    }
    fn contiguous_axis(&self) -> usize {
        0
    }
    fn read_box(&self, lo: [u64; 3], size: [u64; 3], out: &mut [f32]) -> Result<()> {
        let fd = self.fine.dims();
        let flat = self.dim == Dim::Two;
        let flo = [0, 1, 2].map(|a| if flat && a == 2 { 0 } else { 2 * lo[a] });
        let fhi = [0, 1, 2].map(|a| {
            if flat && a == 2 {
                1
            } else {
                (2 * (lo[a] + size[a])).min(fd[a])
            }
        });
        let fsz = [0, 1, 2].map(|a| fhi[a] - flo[a]);
        let mut fine = vec![0f32; (fsz[0] * fsz[1] * fsz[2]) as usize];
        self.fine.read_box(flo, fsz, &mut fine)?;
        let dz: &[u64] = if flat { &[0] } else { &[0, 1] };
        let fidx = |a: usize, c: u64, d: u64| -> usize {
            if flat && a == 2 {
                0
            } else {
                ((2 * c + d).min(fd[a] - 1) - flo[a]) as usize
            }
        };
        out.par_chunks_mut((size[0] * size[1]) as usize)
            .enumerate()
            .for_each(|(zi, plane)| {
                let cz = lo[2] + zi as u64;
                let mut kids = [0f32; 8];
                for yi in 0..size[1] {
                    let cy = lo[1] + yi;
                    for xi in 0..size[0] {
                        let cx = lo[0] + xi;
                        let mut n = 0;
                        for &ddz in dz {
                            let z = fidx(2, cz, ddz);
                            for ddy in 0..2 {
                                let y = fidx(1, cy, ddy);
                                for ddx in 0..2 {
                                    let x = fidx(0, cx, ddx);
                                    kids[n] = fine[(z * fsz[1] as usize + y) * fsz[0] as usize + x];
                                    n += 1;
                                }
                            }
                        }
                        plane[(yi * size[0] + xi) as usize] = self.filter.apply(&kids[..n]);
                    }
                }
            });
        Ok(())
    }
}
