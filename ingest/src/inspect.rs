//! Store summaries, full verification, and the level-0 digest.

use anyhow::{Context, Result};
use indicatif::ProgressBar;
use rayon::prelude::*;
use std::fmt::Write as _;
use std::path::Path;
use strata_common::digest::DigestAcc;
use strata_common::store::{PageStore, PAGE_COMPRESSED, PAGE_CONSTANT, PAGE_EMPTY};

/// What `inspect` found.
#[derive(Clone, Debug)]
pub struct Inspection {
    /// Human-readable report, one fact per line; the last line is `digest: <hex>`.
    pub text: String,
    /// Digest of the decoded level-0 samples.
    pub digest: u64,
    /// Pages whose checksum was verified (0 without `verify`).
    pub verified_pages: u64,
}

/// Digest of the decoded level-0 samples of an open store, computed page by page in parallel.
pub fn level0_digest(store: &PageStore, progress: &ProgressBar) -> Result<DigestAcc> {
    let pyr = store.pyramid();
    let dims = pyr.level(0).dims;
    let pd = pyr.page_dims().map(|v| v as usize);
    let bricks = pyr.bricks_in_z_order(0);
    bricks
        .par_iter()
        .map(|&br| -> Result<DigestAcc> {
            let page = store.read_page(pyr.id(0, br))?;
            let r = pyr.core_range(0, br);
            let o = pyr.page_origin(br);
            let mut acc = DigestAcc::default();
            for z in r[2].0..r[2].1 {
                for y in r[1].0..r[1].1 {
                    let prow =
                        (((z as i64 - o[2]) as usize) * pd[1] + (y as i64 - o[1]) as usize) * pd[0];
                    let grow = (z * dims[1] + y) * dims[0];
                    for x in r[0].0..r[0].1 {
                        acc.add(grow + x, page.samples[prow + (x as i64 - o[0]) as usize]);
                    }
                }
            }
            progress.inc(1);
            Ok(acc)
        })
        .try_reduce(DigestAcc::default, |a, b| Ok(a.combine(b)))
}

/// Summarizes a store; with `verify`, reads every page of every level, checks its checksum
/// and decodes it, and checks the digest against the one recorded at ingest.
pub fn inspect(path: &Path, verify: bool, progress: &ProgressBar) -> Result<Inspection> {
    let store = PageStore::open(path)?;
    let h = store.header();
    let pyr = store.pyramid();
    let mut t = String::new();
    let _ = writeln!(t, "store: {}", path.display());
    let _ = writeln!(t, "name: {}", h.name);
    let _ = writeln!(t, "kind: {:?}", h.kind);
    let _ = writeln!(t, "dims: {} x {} x {}", h.dims[0], h.dims[1], h.dims[2]);
    let _ = writeln!(t, "sample type: {}", h.sample_type.name());
    let _ = writeln!(
        t,
        "value range: {} .. {}",
        h.value_range[0], h.value_range[1]
    );
    if let Some(nd) = h.no_data {
        let _ = writeln!(t, "no-data sentinel: {nd}");
    }
    let total = h.dims.iter().product::<u64>();
    let _ = writeln!(
        t,
        "valid samples: {} of {} ({} no-data)",
        h.valid_samples,
        total,
        total - h.valid_samples
    );
    match &h.stats {
        Some(s) => {
            let list = |v: &[[f64; 2]]| {
                v.iter()
                    .map(|[p, x]| format!("p{p} {x:.6}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            let _ = writeln!(t, "mean: {:.6}, rms: {:.6}", s.mean, s.rms);
            let _ = writeln!(
                t,
                "percentiles (within {:.2e} relative): {}",
                s.resolution,
                list(&s.percentiles)
            );
            let _ = writeln!(t, "percentiles of |value|: {}", list(&s.abs_percentiles));
        }
        None => {
            let _ = writeln!(
                t,
                "statistics: none (a format-1 store, or no valid sample; re-ingest to compute them)"
            );
        }
    }
    let _ = writeln!(
        t,
        "page: {}{} samples, border {}, core {} ({:.1}% border overhead)",
        h.page_size,
        if pyr.dim() == strata_common::pyramid::Dim::Three {
            "³"
        } else {
            "²"
        },
        h.border,
        pyr.core(),
        100.0 * pyr.border_overhead()
    );
    let _ = writeln!(t, "coarsening filter: {}", h.filter.name());
    let _ = writeln!(t, "levels: {}", h.levels);
    for (l, lev) in pyr.levels().iter().enumerate() {
        let es: Vec<_> = store
            .index()
            .iter()
            .filter(|e| e.id.level() as usize == l)
            .collect();
        let cst = es.iter().filter(|e| e.flags & PAGE_CONSTANT != 0).count();
        let emp = es.iter().filter(|e| e.flags & PAGE_EMPTY != 0).count();
        let bytes: u64 = es.iter().map(|e| e.stored_len as u64).sum();
        let _ = writeln!(
            t,
            "  level {l}: {} x {} x {} samples, {} x {} x {} = {} pages ({cst} constant, {emp} empty), {bytes} bytes",
            lev.dims[0],
            lev.dims[1],
            lev.dims[2],
            lev.bricks[0],
            lev.bricks[1],
            lev.bricks[2],
            es.len()
        );
    }
    let stored: u64 = store.index().iter().map(|e| e.stored_len as u64).sum();
    let payload_pages = store.index().iter().filter(|e| e.has_payload()).count() as u64;
    let compressed = store
        .index()
        .iter()
        .filter(|e| e.flags & PAGE_COMPRESSED != 0)
        .count();
    let raw = payload_pages * h.page_raw_len() as u64;
    let _ = writeln!(
        t,
        "compression: {} ({compressed} of {payload_pages} stored pages compressed)",
        h.compression.name()
    );
    let _ = writeln!(
        t,
        "bytes: {} file, {stored} page payload, {raw} uncompressed payload, ratio {:.3}",
        store.file_len(),
        if stored > 0 {
            raw as f64 / stored as f64
        } else {
            1.0
        }
    );
    let source_bytes = total * h.sample_type.size() as u64;
    let _ = writeln!(
        t,
        "size vs level-0 samples: {:.3}x",
        store.file_len() as f64 / source_bytes.max(1) as f64
    );
    let _ = writeln!(t, "transform (index -> world): {:?}", h.transform.rows);
    let _ = writeln!(
        t,
        "units: lateral {}, vertical {}{}",
        h.units.lateral,
        h.units.vertical,
        match h.vertical_domain {
            Some(d) => format!(" ({})", d.name()),
            None => String::new(),
        }
    );
    if let Some(s) = &h.survey {
        let _ = writeln!(
            t,
            "survey grid: inlines {}..{} step {} ({}), crosslines {}..{} step {} ({})",
            s.inline0,
            s.inline0 + s.inline_step * (s.n_inline - 1) as f64,
            s.inline_step,
            s.n_inline,
            s.xline0,
            s.xline0 + s.xline_step * (s.n_xline - 1) as f64,
            s.xline_step,
            s.n_xline
        );
    }
    if !h.source.is_empty() {
        let _ = writeln!(t, "source: {}", h.source.lines().next().unwrap_or(""));
    }

    let mut verified = 0;
    if verify {
        progress.set_length(store.index().len() as u64 + pyr.level(0).page_count());
        let results: Vec<_> = store
            .index()
            .par_iter()
            .map(|e| {
                let r = store.read_page(e.id).map(|_| ());
                progress.inc(1);
                r
            })
            .collect();
        for r in results {
            r?;
            verified += 1;
        }
    } else {
        progress.set_length(pyr.level(0).page_count());
    }
    let digest = level0_digest(&store, progress)?.finish(h.dims);
    if verify {
        anyhow::ensure!(
            digest == h.digest,
            "{}: level-0 digest {digest:016x} does not match the {:016x} recorded at ingest",
            path.display(),
            h.digest
        );
        let _ = writeln!(
            t,
            "verified: {verified} pages, all checksums match, digest matches ingest"
        );
    }
    let _ = writeln!(t, "digest: {digest:016x}");
    Ok(Inspection {
        text: t,
        digest,
        verified_pages: verified,
    })
}

/// Reassembles one whole level of a store (for tests and tools; holds the level in memory) from its pages' cores (x fastest).
pub fn level_grid(
    store: &PageStore,
    level: usize,
) -> Result<Vec<f32>, strata_common::store::StoreError> {
    let pyr = store.pyramid();
    let dims = pyr.level(level).dims;
    let pd = pyr.page_dims().map(|v| v as usize);
    let mut out = vec![0f32; (dims[0] * dims[1] * dims[2]) as usize];
    for br in pyr.bricks_in_z_order(level) {
        let page = store.read_page(pyr.id(level, br))?;
        let r = pyr.core_range(level, br);
        let o = pyr.page_origin(br);
        for z in r[2].0..r[2].1 {
            for y in r[1].0..r[1].1 {
                for x in r[0].0..r[0].1 {
                    let p = (((z as i64 - o[2]) as usize) * pd[1] + (y as i64 - o[1]) as usize)
                        * pd[0]
                        + (x as i64 - o[0]) as usize;
                    out[((z * dims[1] + y) * dims[0] + x) as usize] = page.samples[p];
                }
            }
        }
    }
    Ok(out)
}

/// Opens a store with a message that names it.
pub fn open_store(path: &Path) -> Result<PageStore> {
    PageStore::open(path).with_context(|| format!("cannot open page store {}", path.display()))
}
