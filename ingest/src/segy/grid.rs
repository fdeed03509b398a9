//! Grid fit: trace headers to an inline/crossline grid, the traces at each node (one, or a
//! pre-stack gather's to stack), and the grid's world placement.

use super::scan::TraceHdr;
use super::{SegyOptions, MAX_FIT_POINTS, MAX_GRID_CELLS_PER_TRACE};
use anyhow::{bail, Result};
use std::path::Path;
use strata_common::geo::{fit_affine2, Affine2, AffineFit, SurveyGrid};

/// Which traces (0-based, file order) make each grid node, `i·n_xline + j`.
pub(crate) enum TraceTable {
    /// At most one trace per node; `u32::MAX` = none.
    One(Vec<u32>),
    /// A gather per node, averaged (`--stack`): node `n`'s traces are
    /// `traces[start[n]..start[n + 1]]`.
    Stack { start: Vec<u32>, traces: Vec<u32> },
}

impl TraceTable {
    /// The traces of node `n`.
    pub(crate) fn at(&self, n: usize) -> &[u32] {
        match self {
            TraceTable::One(t) if t[n] == u32::MAX => &[],
            TraceTable::One(t) => std::slice::from_ref(&t[n]),
            TraceTable::Stack { start, traces } => {
                &traces[start[n] as usize..start[n + 1] as usize]
            }
        }
    }
}

/// What the grid fit found.
pub(crate) struct Grid {
    pub(crate) survey: SurveyGrid,
    pub(crate) fit: Option<AffineFit>,
    /// `"CDP"`, `"source"` or `"none"`.
    pub(crate) coordinates: &'static str,
    pub(crate) table: TraceTable,
    /// Grid nodes without a trace.
    pub(crate) missing: u64,
    /// Most traces at one node among the traces used.
    pub(crate) max_fold: u32,
    /// Traces that make the grid (all, or those of the chosen offset).
    pub(crate) traces_used: u64,
    /// Distinct offsets (byte 37) over the whole file.
    pub(crate) distinct_offsets: u64,
    /// The first trace (file order) the grid uses.
    pub(crate) first_used: u32,
}

/// Places the traces `hdrs` (all of the file's, in file order) on their grid.
pub(crate) fn fit_grid(
    path: &Path,
    hdrs: &[TraceHdr],
    data_start: u64,
    trace_bytes: u64,
    opts: &SegyOptions,
    warnings: &mut Vec<String>,
) -> Result<Grid> {
    let p = path.display();
    let trace_count = hdrs.len() as u64;
    let mut offsets: Vec<i32> = hdrs.iter().map(|h| h.offset).collect();
    offsets.sort_unstable();
    offsets.dedup();
    let distinct_offsets = offsets.len() as u64;
    let list = |v: &[i32]| {
        let mut s = v
            .iter()
            .take(12)
            .map(|o| o.to_string())
            .collect::<Vec<_>>()
            .join(", ");
        if v.len() > 12 {
            s.push_str(&format!(", ... ({} in all)", v.len()));
        }
        s
    };
    // The traces that make the grid.
    let used: Vec<u32> = match opts.offset {
        Some(o) => {
            let u: Vec<u32> = (0..trace_count as u32)
                .filter(|&t| hdrs[t as usize].offset == o)
                .collect();
            if u.is_empty() {
                bail!(
                    "{p}: --offset {o}: no trace has offset {o} (trace header byte 37); the file's offsets are {}",
                    list(&offsets)
                );
            }
            u
        }
        None => (0..trace_count as u32).collect(),
    };
    let used_hdrs = || used.iter().map(|&t| &hdrs[t as usize]);
    let (il0, il_step, n_inline) = axis_of(used_hdrs().map(|h| h.il));
    let (xl0, xl_step, n_xline) = axis_of(used_hdrs().map(|h| h.xl));
    let n_used = used.len() as u64;
    let cells = n_inline as u128 * n_xline as u128;
    if cells > MAX_GRID_CELLS_PER_TRACE as u128 * n_used as u128 {
        let (il1, xl1) = (
            il0 + (n_inline as i64 - 1) * il_step,
            xl0 + (n_xline as i64 - 1) * xl_step,
        );
        bail!(
            "{p}: inline numbers (trace byte {}) {il0}..{il1} step {il_step} and crossline numbers (trace byte {}) \
             {xl0}..{xl1} step {xl_step} span a {n_inline} x {n_xline} grid, more than {MAX_GRID_CELLS_PER_TRACE} \
             times the {n_used} traces; the numbers are probably not at these byte positions (common choices: \
             189/193 or 9/21)",
            opts.inline_byte,
            opts.xline_byte
        );
    }
    let cells = cells as usize;
    let node_of = |h: &TraceHdr| {
        ((h.il as i64 - il0) / il_step) as usize * n_xline as usize
            + ((h.xl as i64 - xl0) / xl_step) as usize
    };
    // Traces per node.
    let mut fold = vec![0u32; cells];
    for h in used_hdrs() {
        fold[node_of(h)] += 1;
    }
    let max_fold = fold.iter().copied().max().unwrap_or(0);
    let occupied = fold.iter().filter(|&&f| f > 0).count() as u64;
    let table = if max_fold <= 1 {
        let mut one = vec![u32::MAX; cells];
        for &t in &used {
            one[node_of(&hdrs[t as usize])] = t;
        }
        TraceTable::One(one)
    } else if opts.stack {
        let mut start = Vec::with_capacity(cells + 1);
        let mut acc = 0u32;
        start.push(0);
        for &f in &fold {
            acc += f;
            start.push(acc);
        }
        let mut fill = start.clone();
        let mut traces = vec![0u32; used.len()];
        for &t in &used {
            let n = node_of(&hdrs[t as usize]);
            traces[fill[n] as usize] = t;
            fill[n] += 1;
        }
        warnings.push(format!(
            "stacked {n_used} traces onto {occupied} grid nodes (up to {max_fold} per node, their mean)"
        ));
        TraceTable::Stack { start, traces }
    } else {
        // Two traces at one node: name them, and say whether the file is a pre-stack one.
        let mut seen = vec![u32::MAX; cells];
        let (a, b) = used
            .iter()
            .find_map(|&t| {
                let slot = &mut seen[node_of(&hdrs[t as usize])];
                if *slot != u32::MAX {
                    return Some((*slot, t));
                }
                *slot = t;
                None
            })
            .expect("a node with two traces");
        let (ha, hb) = (&hdrs[a as usize], &hdrs[b as usize]);
        let at = |t: u32| data_start + t as u64 * trace_bytes;
        let pair = format!(
            "inline {} crossline {}: trace {} at byte {} (offset {}) and trace {} at byte {} (offset {})",
            ha.il,
            ha.xl,
            a + 1,
            at(a),
            ha.offset,
            b + 1,
            at(b),
            hb.offset
        );
        if opts.offset.is_none() && distinct_offsets > 1 {
            bail!(
                "{p}: the file is pre-stack: up to {max_fold} traces per inline/crossline node, told apart by {} \
                 distinct offsets (trace header byte 37): {}; e.g. {pair}. Ingest one offset with --offset N (e.g. \
                 --offset {}), or average each node's traces with --stack",
                distinct_offsets,
                list(&offsets),
                offsets[0]
            );
        }
        let (at_offset, or_stack) = match opts.offset {
            Some(o) => (format!(" with offset {o}"), ""),
            None => (
                String::new(),
                "; to average the traces of each node, pass --stack",
            ),
        };
        bail!(
            "{p}: duplicate trace{at_offset} for {pair}; up to {max_fold} traces share a node. If the inline and \
             crossline numbers are not at trace bytes {}/{}, pass --inline-byte and --xline-byte (common choices: \
             189/193 or 9/21){or_stack}",
            opts.inline_byte,
            opts.xline_byte
        );
    };
    let missing = cells as u64 - occupied;
    if missing > 0 {
        warnings.push(format!(
            "{missing} of {cells} grid nodes ({n_inline} inlines x {n_xline} crosslines) have no trace; \
             they read as no-data"
        ));
    }

    // World placement.
    let use_cdp = used_hdrs().any(|h| h.cx != 0 || h.cy != 0);
    let use_src = !use_cdp && used_hdrs().any(|h| h.sx != 0 || h.sy != 0);
    let coordinates = if use_cdp {
        "CDP"
    } else if use_src {
        warnings.push(
            "CDP X/Y (trace bytes 181/185) are all zero; placed the grid with source X/Y (73/77)"
                .into(),
        );
        "source"
    } else {
        "none"
    };
    let world = |h: &TraceHdr| {
        let (x, y) = if use_cdp { (h.cx, h.cy) } else { (h.sx, h.sy) };
        let s = h.scalar as f64;
        let f = |v: i32| {
            let v = v as f64;
            if s < 0.0 {
                v / -s
            } else if s > 0.0 {
                v * s
            } else {
                v
            }
        };
        [f(x), f(y)]
    };
    let grid_of = |h: &TraceHdr| {
        [
            ((h.il as i64 - il0) / il_step) as f64,
            ((h.xl as i64 - xl0) / xl_step) as f64,
        ]
    };
    let mut fit = None;
    if coordinates == "none" {
        warnings.push(
            "trace coordinates (CDP 181/185 and source 73/77) are all zero; world placement is 1 unit per grid index"
                .into(),
        );
    } else {
        let stride = used.len().div_ceil(MAX_FIT_POINTS).max(1);
        let pts: Vec<([f64; 2], [f64; 2])> = used_hdrs()
            .step_by(stride)
            .map(|h| (grid_of(h), world(h)))
            .collect();
        match fit_affine2(&pts).filter(|f| is_usable_map(&f.map)) {
            None => warnings.push(format!(
                "cannot place the grid in the world from the {coordinates} coordinates ({n_inline} inlines x \
                 {n_xline} crosslines; a single line or coincident points); world placement is 1 unit per grid index"
            )),
            Some(f) => {
                // Residuals over every trace used.
                let (mut s2, mut mx) = (0.0f64, 0.0f64);
                for h in used_hdrs() {
                    let a = f.map.apply(grid_of(h));
                    let w = world(h);
                    let d = (a[0] - w[0]).hypot(a[1] - w[1]);
                    s2 += d * d;
                    mx = mx.max(d);
                }
                let fit_all = AffineFit { map: f.map, rms_residual: (s2 / used.len() as f64).sqrt(), max_residual: mx };
                let r = &f.map.rows;
                let bin = (r[0][0].hypot(r[1][0])).min(r[0][1].hypot(r[1][1]));
                if fit_all.max_residual > 0.25 * bin {
                    warnings.push(format!(
                        "trace coordinates depart from a regular grid by up to {:.3} (rms {:.3}) with bins of {:.3}",
                        fit_all.max_residual, fit_all.rms_residual, bin
                    ));
                }
                fit = Some(fit_all);
            }
        }
    }
    let to_world = fit.map(|f| f.map).unwrap_or(Affine2::IDENTITY);
    let survey = SurveyGrid {
        inline0: il0 as f64,
        inline_step: il_step as f64,
        n_inline,
        xline0: xl0 as f64,
        xline_step: xl_step as f64,
        n_xline,
        to_world,
    };
    Ok(Grid {
        survey,
        fit,
        coordinates,
        table,
        missing,
        max_fold,
        traces_used: n_used,
        distinct_offsets,
        first_used: used[0],
    })
}

/// First value, step (gcd of the gaps between distinct values) and count of a line axis.
pub(crate) fn axis_of(values: impl Iterator<Item = i32>) -> (i64, i64, u64) {
    let mut v: Vec<i32> = values.collect();
    v.sort_unstable();
    v.dedup();
    let (first, last) = (v[0] as i64, v[v.len() - 1] as i64);
    let step = v
        .windows(2)
        .fold(0i64, |g, w| gcd(g, w[1] as i64 - w[0] as i64));
    let step = if step == 0 { 1 } else { step };
    (first, step, ((last - first) / step) as u64 + 1)
}

fn gcd(mut a: i64, mut b: i64) -> i64 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a.abs()
}

/// Whether a grid-to-world map has finite coefficients and two independent, non-zero bins.
pub(crate) fn is_usable_map(m: &Affine2) -> bool {
    let r = &m.rows;
    let (a, b, c, d) = (r[0][0], r[0][1], r[1][0], r[1][1]);
    let (li, lj) = (a.hypot(c), b.hypot(d));
    r.iter().flatten().all(|v| v.is_finite())
        && li > 0.0
        && lj > 0.0
        && (a * d - b * c).abs() > 1e-6 * li * lj
}
