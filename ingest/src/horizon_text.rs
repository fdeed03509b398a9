//! Interpreted horizons from text exports.
//!
//! Three layouts are read, all as plain text with one record per line:
//!
//! * [`HorizonFormat::IlXlZ`]: point list `inline crossline z`;
//! * [`HorizonFormat::XyIlXlZ`]: point list `x y inline crossline z` (the usual
//!   OpendTect / Petrel "X Y Inline Crossline Z" export);
//! * [`HorizonFormat::Grid`]: a dense grid, one text row per inline and one column per
//!   crossline (what `numpy.savetxt` writes for a `(n_inline, n_xline)` array).
//!
//! Point lists may come in any order and may be sparse; missing nodes become holes (`NaN`).
//! The lateral grid is inferred from the distinct inline / crossline numbers (minimum and
//! greatest common step), unless the caller passes the [`SurveyGrid`] of a seismic store,
//! in which case the horizon is resampled onto exactly that grid and points off it are
//! dropped and counted.
//!
//! Lines starting with `#`, `!` or `//` and blank lines are comments. One header line of
//! column names at the top is skipped. Fields are separated by any mix of whitespace, `,`
//! and `;`. The tokens `nan`, `-nan`, `NULL` (any case) and the optional null value
//! (e.g. `-999.25`) are holes.
//!
//! Memory: the file is streamed twice (pass 1: validation, geometry, affine-fit sums;
//! pass 2: filling the grid and the fit residuals), so the output grid is the only
//! allocation that grows with the input. Errors name the file, the 1-based line and what
//! was expected versus found; nothing in here panics on bad input.

use std::fs::File;
use std::io::{BufRead, BufReader};
use std::path::Path;

use anyhow::{anyhow, bail, Result};
use strata_common::geo::{Affine2, AffineFit, SurveyGrid};

/// Layout of a horizon text file.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq)]
pub enum HorizonFormat {
    /// Decide from the first data line: 3 columns → [`Self::IlXlZ`], 5 → [`Self::XyIlXlZ`],
    /// anything else → [`Self::Grid`].
    #[default]
    Auto,
    /// Point list `inline crossline z`.
    IlXlZ,
    /// Point list `x y inline crossline z`.
    XyIlXlZ,
    /// Dense grid: text row = inline index, text column = crossline index.
    Grid,
}

/// How to read a horizon text file.
#[derive(Clone, Debug, PartialEq)]
pub struct HorizonParseOptions {
    /// File layout.
    pub format: HorizonFormat,
    /// A height value that marks a hole (e.g. `-999.25`), compared exactly as `f64`.
    pub null_value: Option<f64>,
    /// The lateral grid of a seismic store: when given, the output uses exactly this grid
    /// instead of one inferred from the file, and nodes off it are dropped.
    pub survey: Option<SurveyGrid>,
    /// Grid format only: inline and crossline number of text row 0 / column 0.
    pub grid_origin: (f64, f64),
    /// Grid format only: inline and crossline number increment per text row / column.
    pub grid_step: (f64, f64),
}

impl Default for HorizonParseOptions {
    fn default() -> Self {
        Self {
            format: HorizonFormat::Auto,
            null_value: None,
            survey: None,
            grid_origin: (0.0, 0.0),
            grid_step: (1.0, 1.0),
        }
    }
}

/// A horizon on a regular lateral grid.
#[derive(Clone, Debug, PartialEq)]
pub struct HorizonGrid {
    /// The lateral grid (inferred from the file, or the survey passed in the options).
    pub survey: SurveyGrid,
    /// `n_inline · n_xline` heights, inline index fastest: `heights[j * n_inline + i]`.
    /// `NaN` = hole.
    pub heights: Vec<f32>,
    /// Least-squares fit of grid index → world (x, y) over all points, when the file has
    /// X/Y columns. Its residuals tell how regular the exported coordinates are.
    pub fit: Option<AffineFit>,
    /// Nodes read from the file (points of a point list, cells of a grid), holes included.
    pub nodes_read: u64,
    /// Output grid cells without a height (`NaN`).
    pub holes: u64,
    /// Nodes read that do not fall on a node of the output grid (only with a survey grid).
    pub dropped: u64,
    /// Things the user should know about (duplicates, dropped nodes, guessed placement).
    pub warnings: Vec<String>,
}

/// Longest line accepted; anything longer is taken to be a binary or corrupt file.
const MAX_LINE_BYTES: usize = 256 << 20;

/// An inferred grid may have at most this many nodes per point read.
const MAX_NODES_PER_POINT: f64 = 64.0;

/// Bit pattern of a quiet NaN marking "no value written yet" while filling the grid, so
/// duplicates are found without a second bitmap. Holes are written as `f32::NAN`, which
/// has a different payload; unset cells become `f32::NAN` before the grid is returned.
const UNSET_BITS: u32 = 0x7FC0_5EA1;

/// Reads a horizon text file onto a regular grid.
///
/// See the [module documentation](self) for the formats and rules.
pub fn parse_horizon(path: &Path, opts: &HorizonParseOptions) -> Result<HorizonGrid> {
    let file = path.display().to_string();
    if let Some(s) = &opts.survey {
        check_survey(&file, s)?;
    }
    if let Some(n) = opts.null_value {
        // Heights are finite: an infinite null (`--null 1e400`) would mark nothing.
        if !n.is_finite() {
            bail!("{file}: the null value must be a finite number, got {n}");
        }
    }
    let format = match opts.format {
        HorizonFormat::Auto => detect_format(path, &file)?,
        f => f,
    };
    let out = match format {
        HorizonFormat::IlXlZ => parse_points(path, &file, opts, false),
        HorizonFormat::XyIlXlZ => parse_points(path, &file, opts, true),
        HorizonFormat::Grid | HorizonFormat::Auto => parse_grid(path, &file, opts),
    }?;
    tracing::debug!(
        file = %file,
        n_inline = out.survey.n_inline,
        n_xline = out.survey.n_xline,
        nodes_read = out.nodes_read,
        holes = out.holes,
        dropped = out.dropped,
        "horizon read"
    );
    Ok(out)
}

// ---------------------------------------------------------------------------------------
// Line scanning
// ---------------------------------------------------------------------------------------

/// One classified line handed to a scan callback.
enum Event<'a> {
    /// A comment line (text after the comment marker, lossily decoded).
    Comment(&'a str),
    /// A data line: 1-based line number and the trimmed text.
    Data(u64, &'a str),
}

/// Streams `path` line by line, skipping blank lines and the single header line, and
/// calls `f` for comments and data lines. `f` returns `Ok(false)` to stop early.
/// Returns the number of data lines seen and the header line, if one was skipped.
fn scan_file(
    path: &Path,
    file: &str,
    mut f: impl FnMut(Event<'_>) -> Result<bool>,
) -> Result<ScanEnd> {
    let handle = File::open(path).map_err(|e| anyhow!("{file}: cannot open: {e}"))?;
    let mut reader = BufReader::with_capacity(1 << 20, handle);
    let mut buf: Vec<u8> = Vec::with_capacity(4096);
    let mut line_no: u64 = 0;
    let mut end = ScanEnd {
        data_lines: 0,
        header: None,
    };
    let mut header_decided = false;
    loop {
        if !read_line(&mut reader, &mut buf, file, line_no + 1)? {
            return Ok(end);
        }
        line_no += 1;
        let mut bytes: &[u8] = &buf;
        if line_no == 1 {
            bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
        }
        let bytes = bytes.trim_ascii();
        if bytes.is_empty() {
            continue;
        }
        let marker = if bytes[0] == b'#' || bytes[0] == b'!' {
            Some(1)
        } else if bytes.starts_with(b"//") {
            Some(2)
        } else {
            None
        };
        if let Some(m) = marker {
            let text = String::from_utf8_lossy(&bytes[m..]);
            if !f(Event::Comment(&text[..]))? {
                return Ok(end);
            }
            continue;
        }
        let text = std::str::from_utf8(bytes).map_err(|e| {
            anyhow!(
                "{file}:{line_no}: expected text, found a byte that is not UTF-8 at column {}",
                e.valid_up_to() + 1
            )
        })?;
        if !header_decided {
            header_decided = true;
            if looks_like_header(text) {
                end.header = Some(line_no);
                tracing::debug!(file, line = line_no, header = text, "skipping header line");
                continue;
            }
        }
        end.data_lines += 1;
        if !f(Event::Data(line_no, text))? {
            return Ok(end);
        }
    }
}

/// What a scan saw.
struct ScanEnd {
    data_lines: u64,
    header: Option<u64>,
}

/// Reads one line (without its `\n`) into `buf`; `false` at end of file.
fn read_line(
    reader: &mut impl BufRead,
    buf: &mut Vec<u8>,
    file: &str,
    line_no: u64,
) -> Result<bool> {
    buf.clear();
    let mut any = false;
    loop {
        let avail = match reader.fill_buf() {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => bail!("{file}:{line_no}: read error: {e}"),
        };
        if avail.is_empty() {
            lone_cr(buf, file, line_no)?;
            return Ok(any);
        }
        any = true;
        if let Some(p) = avail.iter().position(|&b| b == b'\n') {
            buf.extend_from_slice(&avail[..p]);
            reader.consume(p + 1);
            lone_cr(buf, file, line_no)?;
            return Ok(true);
        }
        let n = avail.len();
        buf.extend_from_slice(avail);
        reader.consume(n);
        if buf.len() > MAX_LINE_BYTES {
            bail!(
                "{file}:{line_no}: line longer than {} MiB; this does not look like a text horizon",
                MAX_LINE_BYTES >> 20
            );
        }
    }
}

/// Refuses a carriage return inside a line (one ending it, CRLF, is fine): a file with
/// CR-only line endings (classic Mac OS) would otherwise read as one long line of every
/// point, and could pass as a one-row grid.
fn lone_cr(line: &[u8], file: &str, line_no: u64) -> Result<()> {
    let body = line.strip_suffix(b"\r").unwrap_or(line);
    if body.contains(&b'\r') {
        bail!(
            "{file}:{line_no}: a carriage return inside the line: the file's lines end in CR \
             alone (classic Mac OS); convert them to LF or CRLF"
        );
    }
    Ok(())
}

/// Fields of a data line: separated by whitespace, commas or semicolons.
fn tokens(line: &str) -> impl Iterator<Item = &str> {
    line.split(|c: char| c.is_whitespace() || c == ',' || c == ';')
        .filter(|t| !t.is_empty())
}

/// Whether a token spells a hole.
fn is_hole_token(t: &str) -> bool {
    ["nan", "-nan", "+nan", "null"]
        .iter()
        .any(|h| t.eq_ignore_ascii_case(h))
}

/// A line of column names: at least half of its tokens are neither numbers nor holes.
fn looks_like_header(line: &str) -> bool {
    let (mut n, mut words) = (0usize, 0usize);
    for t in tokens(line) {
        n += 1;
        if !is_hole_token(t) && t.parse::<f64>().is_err() {
            words += 1;
        }
    }
    words > 0 && 2 * words >= n
}

/// Decides the format from the first data line's column count.
fn detect_format(path: &Path, file: &str) -> Result<HorizonFormat> {
    let mut count = None;
    let end = scan_file(path, file, |ev| {
        Ok(match ev {
            Event::Comment(_) => true,
            Event::Data(_, line) => {
                count = Some(tokens(line).count());
                false
            }
        })
    })?;
    match count {
        None => Err(no_data(file, &end)),
        Some(3) => Ok(HorizonFormat::IlXlZ),
        Some(5) => Ok(HorizonFormat::XyIlXlZ),
        Some(_) => Ok(HorizonFormat::Grid),
    }
}

fn no_data(file: &str, end: &ScanEnd) -> anyhow::Error {
    match end.header {
        Some(h) => anyhow!(
            "{file}: expected data lines, found none (only comments and the header at line {h})"
        ),
        None => anyhow!(
            "{file}: expected data lines, found none (the file is empty or holds only comments)"
        ),
    }
}

// ---------------------------------------------------------------------------------------
// Value parsing
// ---------------------------------------------------------------------------------------

/// Parses a height: holes (tokens, NaN, the null value) → `f32::NAN`; ±inf → error.
fn parse_height(tok: &str, null: Option<f64>, file: &str, line: u64, col: usize) -> Result<f32> {
    if is_hole_token(tok) {
        return Ok(f32::NAN);
    }
    let v: f64 = tok
        .parse()
        .map_err(|_| anyhow!("{file}:{line}: expected a number in column {col}, found {tok:?}"))?;
    if v.is_nan() || null == Some(v) {
        return Ok(f32::NAN);
    }
    if v.is_infinite() {
        bail!("{file}:{line}: expected a finite height in column {col}, found {tok:?}");
    }
    let z = v as f32;
    if z.is_infinite() {
        bail!("{file}:{line}: height {tok:?} in column {col} is out of the f32 range");
    }
    Ok(z)
}

/// Parses a finite coordinate (inline, crossline, x or y).
fn parse_coord(tok: &str, what: &str, file: &str, line: u64, col: usize) -> Result<f64> {
    match tok.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => bail!("{file}:{line}: expected a finite {what} number in column {col}, found {tok:?}"),
    }
}

/// One record of a point list.
struct Point {
    il: f64,
    xl: f64,
    z: f32,
    xy: Option<[f64; 2]>,
}

/// Splits and parses a point-list line with exactly `ncols` (3 or 5) fields.
fn parse_point(
    line: &str,
    with_xy: bool,
    null: Option<f64>,
    file: &str,
    line_no: u64,
) -> Result<Point> {
    let ncols = if with_xy { 5 } else { 3 };
    let mut f = [""; 5];
    let mut n = 0usize;
    for t in tokens(line) {
        if n < 5 {
            f[n] = t;
        }
        n += 1;
    }
    if n != ncols {
        let layout = if with_xy {
            "X Y Inline Crossline Z"
        } else {
            "Inline Crossline Z"
        };
        bail!("{file}:{line_no}: expected {ncols} columns ({layout}), found {n}");
    }
    let base = if with_xy { 2 } else { 0 };
    let xy = if with_xy {
        Some([
            parse_coord(f[0], "X", file, line_no, 1)?,
            parse_coord(f[1], "Y", file, line_no, 2)?,
        ])
    } else {
        None
    };
    Ok(Point {
        il: parse_coord(f[base], "inline", file, line_no, base + 1)?,
        xl: parse_coord(f[base + 1], "crossline", file, line_no, base + 2)?,
        z: parse_height(f[base + 2], null, file, line_no, base + 3)?,
        xy,
    })
}

// ---------------------------------------------------------------------------------------
// Geometry helpers
// ---------------------------------------------------------------------------------------

fn check_survey(file: &str, s: &SurveyGrid) -> Result<()> {
    let ok = s.inline0.is_finite()
        && s.xline0.is_finite()
        && s.inline_step.is_finite()
        && s.xline_step.is_finite()
        && s.inline_step != 0.0
        && s.xline_step != 0.0
        && s.n_inline > 0
        && s.n_xline > 0
        && s.to_world.rows.iter().flatten().all(|v| v.is_finite());
    if !ok {
        bail!("{file}: the survey grid passed in is invalid (needs finite, non-zero steps and at least one node per axis): {s:?}");
    }
    Ok(())
}

/// Allocates the output grid, every cell `UNSET_BITS`.
fn alloc_grid(file: &str, n_inline: u64, n_xline: u64) -> Result<Vec<f32>> {
    let n = n_inline
        .checked_mul(n_xline)
        .and_then(|n| usize::try_from(n).ok())
        .ok_or_else(|| anyhow!("{file}: a grid of {n_inline} x {n_xline} nodes is too large"))?;
    let mut v = Vec::new();
    v.try_reserve_exact(n).map_err(|_| {
        anyhow!(
            "{file}: cannot allocate a grid of {n_inline} x {n_xline} nodes ({} MiB)",
            (n as u64 * 4) >> 20
        )
    })?;
    v.resize(n, f32::from_bits(UNSET_BITS));
    Ok(v)
}

/// Replaces unset cells by `NaN` and returns the number of holes.
fn finish_grid(heights: &mut [f32]) -> u64 {
    let mut holes = 0;
    for h in heights.iter_mut() {
        if h.is_nan() {
            *h = f32::NAN;
            holes += 1;
        }
    }
    holes
}

/// Node of `(il, xl)` on `g`, allowing `tol` grid steps of misfit.
fn node_of(g: &SurveyGrid, il: f64, xl: f64, tol: f64) -> Option<(u64, u64)> {
    if tol <= 1e-6 {
        return g.index_of(il, xl);
    }
    let fi = (il - g.inline0) / g.inline_step;
    let fj = (xl - g.xline0) / g.xline_step;
    let (i, j) = (fi.round(), fj.round());
    let on = (fi - i).abs() < tol && (fj - j).abs() < tol;
    (on && i >= 0.0 && j >= 0.0 && i < g.n_inline as f64 && j < g.n_xline as f64)
        .then_some((i as u64, j as u64))
}

/// Largest integer below which every `f64` integer is exact.
const EXACT_INT: f64 = 9_007_199_254_740_992.0;

/// Greatest common divisor of two non-negative step candidates: exact for integers,
/// Euclid with a relative tolerance of 1e-6 otherwise.
fn gcd_f64(a: f64, b: f64) -> f64 {
    let (mut a, mut b) = if a >= b { (a, b) } else { (b, a) };
    if b == 0.0 {
        return a;
    }
    if a.fract() == 0.0 && b.fract() == 0.0 && a < EXACT_INT {
        let (mut x, mut y) = (a as u64, b as u64);
        while y != 0 {
            (x, y) = (y, x % y);
        }
        return x as f64;
    }
    // Stop refining once the candidate is far below anything meaningful.
    let floor = a * 1e-12;
    loop {
        let tol = 1e-6 * b;
        let r = a % b;
        if r <= tol || b - r <= tol || b <= floor {
            return b;
        }
        (a, b) = (b, r);
    }
}

/// Running statistics of one axis (inline or crossline numbers).
#[derive(Clone, Copy)]
struct AxisStats {
    min: f64,
    max: f64,
    reference: f64,
    step: f64,
    seen: bool,
}

impl AxisStats {
    fn new() -> Self {
        Self {
            min: f64::INFINITY,
            max: f64::NEG_INFINITY,
            reference: 0.0,
            step: 0.0,
            seen: false,
        }
    }
    fn add(&mut self, v: f64) {
        if !self.seen {
            self.seen = true;
            self.reference = v;
        }
        self.min = self.min.min(v);
        self.max = self.max.max(v);
        let d = (v - self.reference).abs();
        if d > 0.0 && d != self.step {
            self.step = gcd_f64(self.step, d);
        }
    }
    /// (first, step, count) of the inferred axis.
    fn axis(&self) -> (f64, f64, f64) {
        let step = if self.step > 0.0 { self.step } else { 1.0 };
        let n = ((self.max - self.min) / step).round() + 1.0;
        (self.min, step, n)
    }
}

/// Streaming least-squares sums for `(il, xl) ↦ (x, y)`, shifted by the first point so
/// UTM-sized coordinates lose no precision. Same normal equations as
/// [`strata_common::geo::fit_affine2`], without holding the points in memory.
#[derive(Clone, Copy)]
struct FitSums {
    n: f64,
    r: [f64; 4],
    s: [f64; 4],
    sii: f64,
    sij: f64,
    sjj: f64,
    swi: [[f64; 2]; 2],
}

impl FitSums {
    fn new() -> Self {
        Self {
            n: 0.0,
            r: [0.0; 4],
            s: [0.0; 4],
            sii: 0.0,
            sij: 0.0,
            sjj: 0.0,
            swi: [[0.0; 2]; 2],
        }
    }
    fn add(&mut self, il: f64, xl: f64, w: [f64; 2]) {
        if self.n == 0.0 {
            self.r = [il, xl, w[0], w[1]];
        }
        self.n += 1.0;
        let d = [
            il - self.r[0],
            xl - self.r[1],
            w[0] - self.r[2],
            w[1] - self.r[3],
        ];
        for k in 0..4 {
            self.s[k] += d[k];
        }
        self.sii += d[0] * d[0];
        self.sij += d[0] * d[1];
        self.sjj += d[1] * d[1];
        for k in 0..2 {
            self.swi[k][0] += d[2 + k] * d[0];
            self.swi[k][1] += d[2 + k] * d[1];
        }
    }
    /// Solves the fit in shifted (il, xl) space; `None` when the points are collinear.
    fn solve(&self) -> Option<FitSolution> {
        if self.n < 3.0 {
            return None;
        }
        let n = self.n;
        let m = self.s.map(|v| v / n);
        let sii = self.sii - n * m[0] * m[0];
        let sij = self.sij - n * m[0] * m[1];
        let sjj = self.sjj - n * m[1] * m[1];
        let det = sii * sjj - sij * sij;
        if !(det.abs() > 1e-12 * (sii * sjj).max(1e-300)) {
            return None;
        }
        let mut a = [[0.0; 2]; 2];
        let mut c = [0.0; 2];
        for k in 0..2 {
            let rx = self.swi[k][0] - n * m[2 + k] * m[0];
            let ry = self.swi[k][1] - n * m[2 + k] * m[1];
            a[k][0] = (rx * sjj - ry * sij) / det;
            a[k][1] = (ry * sii - rx * sij) / det;
            c[k] = m[2 + k] - a[k][0] * m[0] - a[k][1] * m[1];
        }
        (a.iter().flatten().chain(&c).all(|v| v.is_finite())).then_some(FitSolution {
            r: self.r,
            a,
            c,
        })
    }
}

/// A solved fit in shifted coordinates: `w - r_w = a · (g - r_g) + c`.
struct FitSolution {
    r: [f64; 4],
    a: [[f64; 2]; 2],
    c: [f64; 2],
}

impl FitSolution {
    /// Distance between the fitted and the given world point.
    fn residual(&self, il: f64, xl: f64, w: [f64; 2]) -> f64 {
        let (di, dj) = (il - self.r[0], xl - self.r[1]);
        let ex = self.a[0][0] * di + self.a[0][1] * dj + self.c[0] - (w[0] - self.r[2]);
        let ey = self.a[1][0] * di + self.a[1][1] * dj + self.c[1] - (w[1] - self.r[3]);
        (ex * ex + ey * ey).sqrt()
    }
    /// The map from grid index `(i, j)` of `g` to world.
    fn index_map(&self, g: &SurveyGrid) -> Affine2 {
        let mut rows = [[0.0; 3]; 2];
        for k in 0..2 {
            let [a0, a1] = self.a[k];
            rows[k] = [
                a0 * g.inline_step,
                a1 * g.xline_step,
                self.r[2 + k]
                    + self.c[k]
                    + a0 * (g.inline0 - self.r[0])
                    + a1 * (g.xline0 - self.r[1]),
            ];
        }
        Affine2 { rows }
    }
}

// ---------------------------------------------------------------------------------------
// Point lists
// ---------------------------------------------------------------------------------------

fn parse_points(
    path: &Path,
    file: &str,
    opts: &HorizonParseOptions,
    with_xy: bool,
) -> Result<HorizonGrid> {
    let null = opts.null_value;
    let mut warnings = Vec::new();

    // Pass 1: validate every line, gather the axes and the fit sums.
    let (mut il_stats, mut xl_stats) = (AxisStats::new(), AxisStats::new());
    let mut sums = FitSums::new();
    let mut points: u64 = 0;
    let end = scan_file(path, file, |ev| {
        if let Event::Data(line_no, line) = ev {
            let p = parse_point(line, with_xy, null, file, line_no)?;
            points += 1;
            il_stats.add(p.il);
            xl_stats.add(p.xl);
            if let Some(w) = p.xy {
                sums.add(p.il, p.xl, w);
            }
        }
        Ok(true)
    })?;
    if points == 0 {
        return Err(no_data(file, &end));
    }

    // The output grid.
    let (grid, tol) = match &opts.survey {
        Some(s) => (*s, 1e-6),
        None => {
            let (il0, ils, nil) = il_stats.axis();
            let (xl0, xls, nxl) = xl_stats.axis();
            let nodes = nil * nxl;
            if !(nodes <= MAX_NODES_PER_POINT * points as f64) {
                bail!(
                    "{file}: the inline/crossline numbers do not form a plausible grid: inlines {}..{} step {} and \
                     crosslines {}..{} step {} give {nil} x {nxl} nodes, more than {MAX_NODES_PER_POINT} times the \
                     {points} points read",
                    il_stats.min,
                    il_stats.max,
                    ils,
                    xl_stats.min,
                    xl_stats.max,
                    xls
                );
            }
            let g = SurveyGrid {
                inline0: il0,
                inline_step: ils,
                n_inline: nil as u64,
                xline0: xl0,
                xline_step: xls,
                n_xline: nxl as u64,
                to_world: Affine2::IDENTITY,
            };
            (g, 1e-3)
        }
    };
    let mut grid = grid;
    let solution = if with_xy { sums.solve() } else { None };
    if opts.survey.is_none() {
        match &solution {
            Some(sol) => grid.to_world = sol.index_map(&grid),
            None if with_xy => warnings.push(format!(
                "{file}: the X/Y columns do not determine an affine placement (fewer than 3 points or all on one \
                 line); world coordinates are grid indices"
            )),
            None => warnings.push(format!(
                "{file}: no X/Y columns and no survey grid; world coordinates are grid indices (i, j)"
            )),
        }
    } else if with_xy && solution.is_none() {
        warnings.push(format!(
            "{file}: the X/Y columns do not determine an affine placement; no fit reported"
        ));
    }
    let mut heights = alloc_grid(file, grid.n_inline, grid.n_xline)?;

    // Pass 2: fill the grid, measure the fit residuals.
    let n_inline = grid.n_inline;
    let (mut seen, mut dropped, mut duplicates) = (0u64, 0u64, 0u64);
    let mut first_dup: Option<(u64, f64, f64)> = None;
    let mut first_drop: Option<(u64, f64, f64)> = None;
    let (mut res2, mut res_max) = (0.0f64, 0.0f64);
    scan_file(path, file, |ev| {
        if let Event::Data(line_no, line) = ev {
            let p = parse_point(line, with_xy, null, file, line_no)?;
            seen += 1;
            if let (Some(sol), Some(w)) = (&solution, p.xy) {
                let d = sol.residual(p.il, p.xl, w);
                res2 += d * d;
                res_max = res_max.max(d);
            }
            match node_of(&grid, p.il, p.xl, tol) {
                Some((i, j)) => {
                    // In range: i < n_inline, j < n_xline, and the product fits in usize.
                    let cell = &mut heights[(j * n_inline + i) as usize];
                    if cell.to_bits() != UNSET_BITS {
                        duplicates += 1;
                        first_dup.get_or_insert((line_no, p.il, p.xl));
                    }
                    *cell = if p.z.is_nan() { f32::NAN } else { p.z };
                }
                None => {
                    dropped += 1;
                    first_drop.get_or_insert((line_no, p.il, p.xl));
                }
            }
        }
        Ok(true)
    })?;
    if seen != points {
        bail!("{file}: the file changed while it was read ({points} data lines, then {seen})");
    }
    if duplicates > 0 {
        let (l, il, xl) = first_dup.unwrap_or_default();
        warnings.push(format!(
            "{file}: {duplicates} duplicate node(s) (first at line {l}: inline {il}, crossline {xl}); the last value \
             of each was kept"
        ));
    }
    if dropped > 0 {
        let (l, il, xl) = first_drop.unwrap_or_default();
        let why = if opts.survey.is_some() {
            "outside the survey grid"
        } else {
            "off the inferred grid"
        };
        warnings.push(format!(
            "{file}: dropped {dropped} of {points} point(s) {why} (first at line {l}: inline {il}, crossline {xl})"
        ));
    }
    let fit = solution.map(|sol| AffineFit {
        map: sol.index_map(&grid),
        rms_residual: (res2 / points as f64).sqrt(),
        max_residual: res_max,
    });
    let holes = finish_grid(&mut heights);
    Ok(HorizonGrid {
        survey: grid,
        heights,
        fit,
        nodes_read: points,
        holes,
        dropped,
        warnings,
    })
}

// ---------------------------------------------------------------------------------------
// Dense grids
// ---------------------------------------------------------------------------------------

/// Finds `spacing x: A ..., y: B` (any case) in a comment; both must be finite and non-zero.
fn parse_spacing(comment: &str) -> Option<(f64, f64)> {
    let lower = comment.to_ascii_lowercase();
    let at = lower.find("spacing")?;
    let rest = &lower[at + "spacing".len()..];
    let (x, used) = value_after_key(rest, 'x')?;
    let (y, _) = value_after_key(&rest[used..], 'y')?;
    (x.is_finite() && y.is_finite() && x != 0.0 && y != 0.0).then_some((x, y))
}

/// Finds `key` followed by optional blanks, `:` or `=`, blanks and a number; returns the
/// number and the byte offset just past it.
fn value_after_key(s: &str, key: char) -> Option<(f64, usize)> {
    for (pos, ch) in s.char_indices() {
        if ch != key {
            continue;
        }
        let after = &s[pos + ch.len_utf8()..];
        let t = after.trim_start();
        let Some(t) = t.strip_prefix(':').or_else(|| t.strip_prefix('=')) else {
            continue;
        };
        let t2 = t.trim_start();
        let len = t2
            .char_indices()
            .take_while(|&(k, c)| {
                c.is_ascii_digit() || c == '.' || ((c == '-' || c == '+') && k == 0) || c == 'e'
            })
            .map(|(k, c)| k + c.len_utf8())
            .last()
            .unwrap_or(0);
        // Accept the longest prefix that parses (so "25m" or "1e" stop at the number).
        let v = (1..=len)
            .rev()
            .find_map(|l| t2.get(..l).and_then(|p| p.parse::<f64>().ok()));
        if let Some(v) = v {
            let start = s.len() - t2.len();
            return Some((v, start + len));
        }
    }
    None
}

fn parse_grid(path: &Path, file: &str, opts: &HorizonParseOptions) -> Result<HorizonGrid> {
    let null = opts.null_value;
    let (o, st) = (opts.grid_origin, opts.grid_step);
    if !(o.0.is_finite()
        && o.1.is_finite()
        && st.0.is_finite()
        && st.1.is_finite()
        && st.0 != 0.0
        && st.1 != 0.0)
    {
        bail!("{file}: grid origin {o:?} and step {st:?} must be finite, with non-zero steps");
    }
    let mut warnings = Vec::new();

    // Pass 1: rows, columns, spacing comment. Values are parsed in pass 2.
    let mut spacing = None;
    let mut rows: u64 = 0;
    let mut cols: Option<(usize, u64)> = None;
    let end = scan_file(path, file, |ev| {
        match ev {
            Event::Comment(text) => {
                if spacing.is_none() {
                    spacing = parse_spacing(text);
                }
            }
            Event::Data(line_no, line) => {
                let n = tokens(line).count();
                match cols {
                    None => cols = Some((n, line_no)),
                    Some((expected, first)) if expected != n => bail!(
                        "{file}:{line_no}: expected {expected} values in a grid row (as in line {first}), found {n}"
                    ),
                    Some(_) => {}
                }
                rows += 1;
            }
        }
        Ok(true)
    })?;
    let Some((ncols, _)) = cols else {
        return Err(no_data(file, &end));
    };
    let ncols = ncols as u64;

    let grid = match &opts.survey {
        Some(s) => *s,
        None => {
            let to_world = match spacing {
                Some((a, b)) => {
                    warnings.push(format!(
                        "{file}: placed with the spacing in its comment (x {a}, y {b}) but the origin and azimuth \
                         are unknown; world coordinates start at (0, 0)"
                    ));
                    Affine2 {
                        rows: [[a, 0.0, 0.0], [0.0, b, 0.0]],
                    }
                }
                None => {
                    warnings.push(format!(
                        "{file}: grid without coordinates or survey grid; world coordinates are grid indices (i, j)"
                    ));
                    Affine2::IDENTITY
                }
            };
            SurveyGrid {
                inline0: o.0,
                inline_step: st.0,
                n_inline: rows,
                xline0: o.1,
                xline_step: st.1,
                n_xline: ncols,
                to_world,
            }
        }
    };
    let mut heights = alloc_grid(file, grid.n_inline, grid.n_xline)?;
    let n_inline = grid.n_inline;
    let direct = opts.survey.is_none();

    // Pass 2: values.
    let (mut r, mut dropped) = (0u64, 0u64);
    scan_file(path, file, |ev| {
        if let Event::Data(line_no, line) = ev {
            let mut c = 0u64;
            for tok in tokens(line) {
                let z = parse_height(tok, null, file, line_no, c as usize + 1)?;
                let node = if direct {
                    (r < n_inline && c < grid.n_xline).then_some((r, c))
                } else {
                    grid.index_of(o.0 + r as f64 * st.0, o.1 + c as f64 * st.1)
                };
                match node {
                    Some((i, j)) => heights[(j * n_inline + i) as usize] = z,
                    None => dropped += 1,
                }
                c += 1;
            }
            if c != ncols {
                bail!("{file}:{line_no}: expected {ncols} values in a grid row, found {c}");
            }
            r += 1;
        }
        Ok(true)
    })?;
    if r != rows {
        bail!("{file}: the file changed while it was read ({rows} rows, then {r})");
    }
    let nodes_read = rows * ncols;
    if dropped > 0 {
        warnings.push(format!(
            "{file}: dropped {dropped} of {nodes_read} grid node(s) outside the survey grid (rows/columns mapped with \
             origin {o:?}, step {st:?})"
        ));
    }
    let holes = finish_grid(&mut heights);
    Ok(HorizonGrid {
        survey: grid,
        heights,
        fit: None,
        nodes_read,
        holes,
        dropped,
        warnings,
    })
}

// ---------------------------------------------------------------------------------------
// Tests
// ---------------------------------------------------------------------------------------

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;
    use strata_common::geo::fit_affine2;

    const FS4: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/real/horizons/f3_fs4/F3_Demo_0_FS4.dat"
    );
    const HOR_B: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/real/horizons/penobscot_hor_b/Hor_B.txt"
    );
    const SEABED: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/real/horizons/penobscot_seabed/Penobscot_Seabed.txt"
    );

    /// Writes `text` to a per-process temporary file named after `name`.
    fn temp(name: &str, text: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("strata_horizon_text_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    fn parse(p: &Path) -> Result<HorizonGrid> {
        parse_horizon(p, &HorizonParseOptions::default())
    }

    fn z_range(h: &HorizonGrid) -> (f32, f32) {
        h.heights
            .iter()
            .filter(|v| v.is_finite())
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            })
    }

    fn at(h: &HorizonGrid, i: u64, j: u64) -> f32 {
        h.heights[(j * h.survey.n_inline + i) as usize]
    }

    #[test]
    fn f3_fs4_point_list() {
        let h = parse(Path::new(FS4)).unwrap();
        let s = h.survey;
        assert_eq!((s.n_inline, s.n_xline), (225, 300));
        assert_eq!(
            (s.inline0, s.inline_step, s.xline0, s.xline_step),
            (110.0, 2.0, 550.0, 2.0)
        );
        assert_eq!(h.heights.len(), 225 * 300);
        assert_eq!((h.nodes_read, h.holes, h.dropped), (67_500, 0, 0));
        let (lo, hi) = z_range(&h);
        assert!(
            (lo - 820.536).abs() < 1e-3 && (hi - 1070.645).abs() < 1e-3,
            "{lo}..{hi}"
        );
        // First data line: 612076.10 6073980.89 110 550 1069.591283798217773.
        assert!((at(&h, 0, 0) - 1069.5913).abs() < 1e-3);
        let fit = h.fit.expect("FS4 has X/Y columns");
        println!(
            "FS4 affine fit: rms {:.4} m, max {:.4} m, map {:?}",
            fit.rms_residual, fit.max_residual, fit.map
        );
        assert!(fit.rms_residual < 1.0, "rms {}", fit.rms_residual);
        assert_eq!(s.to_world, fit.map);
        let w = s.to_world.apply([0.0, 0.0]);
        assert!(
            (w[0] - 612076.10).abs() < 2.0 && (w[1] - 6073980.89).abs() < 2.0,
            "{w:?}"
        );
        // Node spacing about 25 m along both axes (inline step 2, so per index ~25 m).
        let dx = s.to_world.apply([1.0, 0.0]);
        let di = ((dx[0] - w[0]).powi(2) + (dx[1] - w[1]).powi(2)).sqrt();
        assert!(di > 10.0 && di < 60.0, "{di}");
        assert!(h.warnings.is_empty(), "{:?}", h.warnings);

        // The streamed fit equals fit_affine2 over the same points.
        let text = std::fs::read_to_string(FS4).unwrap();
        let pts: Vec<([f64; 2], [f64; 2])> = text
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(|l| {
                let v: Vec<f64> = l.split('\t').map(|t| t.parse().unwrap()).collect();
                ([(v[2] - 110.0) / 2.0, (v[3] - 550.0) / 2.0], [v[0], v[1]])
            })
            .collect();
        let reference = fit_affine2(&pts).unwrap();
        assert!(
            (reference.rms_residual - fit.rms_residual).abs() < 1e-6,
            "{reference:?} vs {fit:?}"
        );
        assert!((reference.max_residual - fit.max_residual).abs() < 1e-6);
        for r in 0..2 {
            for k in 0..3 {
                assert!((reference.map.rows[r][k] - fit.map.rows[r][k]).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn penobscot_hor_b_grid() {
        let h = parse(Path::new(HOR_B)).unwrap();
        assert_eq!((h.survey.n_inline, h.survey.n_xline), (250, 200));
        assert_eq!((h.nodes_read, h.holes, h.dropped), (50_000, 0, 0));
        let (lo, hi) = z_range(&h);
        assert_eq!((lo, hi), (8.0, 47.0));
        assert!(h.fit.is_none());
        assert_eq!(h.survey.to_world, Affine2::IDENTITY);
        assert!(
            h.warnings.iter().any(|w| w.contains("grid indices")),
            "{:?}",
            h.warnings
        );
        // Compare with the text: row i, column j.
        let text = std::fs::read_to_string(HOR_B).unwrap();
        let rows: Vec<Vec<f32>> = text
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(|l| l.split_whitespace().map(|t| t.parse().unwrap()).collect())
            .collect();
        assert_eq!(rows.len(), 250);
        for &(i, j) in &[
            (0usize, 0usize),
            (0, 199),
            (249, 0),
            (249, 199),
            (17, 123),
            (200, 5),
            (123, 77),
        ] {
            assert_eq!(at(&h, i as u64, j as u64), rows[i][j], "node ({i}, {j})");
        }
        // Every node, to be sure of the transpose.
        for (i, row) in rows.iter().enumerate() {
            for (j, &v) in row.iter().enumerate() {
                assert_eq!(h.heights[j * 250 + i], v);
            }
        }
    }

    #[test]
    fn penobscot_hor_b_with_origin_and_survey() {
        // The subset header: inline 1207.., crossline 1253.., step 1.
        let opts = HorizonParseOptions {
            grid_origin: (1207.0, 1253.0),
            ..Default::default()
        };
        let h = parse_horizon(Path::new(HOR_B), &opts).unwrap();
        assert_eq!((h.survey.inline0, h.survey.xline0), (1207.0, 1253.0));
        // A survey that covers inlines 1300..1499 and crosslines 1253..1452 (step 1).
        let survey = SurveyGrid {
            inline0: 1300.0,
            inline_step: 1.0,
            n_inline: 200,
            xline0: 1253.0,
            xline_step: 1.0,
            n_xline: 200,
            to_world: Affine2 {
                rows: [[12.5, 0.0, 1000.0], [0.0, 12.5, 2000.0]],
            },
        };
        let opts = HorizonParseOptions {
            survey: Some(survey),
            ..opts
        };
        let g = parse_horizon(Path::new(HOR_B), &opts).unwrap();
        assert_eq!(g.survey, survey);
        // Rows 0..92 (inlines 1207..1299) fall off the survey: 93 rows x 200 columns.
        assert_eq!(g.dropped, 93 * 200);
        // Survey inlines 1457..1499 (43) are not in the file: holes.
        assert_eq!(g.holes, 43 * 200);
        assert_eq!(at(&g, 0, 7), at(&h, 93, 7));
        assert!(
            g.warnings.iter().any(|w| w.contains("dropped 18600")),
            "{:?}",
            g.warnings
        );
    }

    #[test]
    fn penobscot_seabed_grid_with_nan_and_spacing() {
        let h = parse(Path::new(SEABED)).unwrap();
        assert_eq!((h.survey.n_inline, h.survey.n_xline), (601, 481));
        assert_eq!(h.holes, 39_509);
        assert_eq!(h.heights.iter().filter(|v| v.is_finite()).count(), 249_572);
        assert_eq!(h.nodes_read, 601 * 481);
        let (lo, hi) = z_range(&h);
        assert!(
            (lo - 38.39).abs() < 1e-4 && (hi - 85.27).abs() < 1e-4,
            "{lo}..{hi}"
        );
        assert_eq!(
            h.survey.to_world,
            Affine2 {
                rows: [[25.0, 0.0, 0.0], [0.0, 12.5, 0.0]]
            }
        );
        assert!(
            h.warnings.iter().any(|w| w.contains("origin")),
            "{:?}",
            h.warnings
        );
        // Finite values occupy rows 3..597 and columns 3..478 only.
        assert!(at(&h, 0, 240).is_nan() && at(&h, 300, 0).is_nan());
        assert!(at(&h, 300, 240).is_finite());
    }

    #[test]
    fn spacing_phrase() {
        assert_eq!(
            parse_spacing(" Sample spacing x: 25 m, y: 12.5 m"),
            Some((25.0, 12.5))
        );
        assert_eq!(parse_spacing("SPACING X=30m Y = 15"), Some((30.0, 15.0)));
        assert_eq!(parse_spacing("spacing x: 0, y: 1"), None);
        assert_eq!(parse_spacing("units are z-indexes"), None);
    }

    #[test]
    fn sparse_point_list_has_holes_and_gcd_steps() {
        let p = temp(
            "sparse.txt",
            "// exported by hand\n\
             Inline,Crossline,Z\n\
             100, 20, 1.5\n\
             104; 26; 2.5\n\
             \n\
             110 20 NULL\n\
             ! another comment\n\
             106\t24\t-999.25\n\
             102 22 nan\n",
        );
        let opts = HorizonParseOptions {
            null_value: Some(-999.25),
            ..Default::default()
        };
        let h = parse_horizon(&p, &opts).unwrap();
        let s = h.survey;
        assert_eq!((s.inline0, s.inline_step, s.n_inline), (100.0, 2.0, 6));
        assert_eq!((s.xline0, s.xline_step, s.n_xline), (20.0, 2.0, 4));
        assert_eq!(h.nodes_read, 5);
        assert_eq!(h.holes, 24 - 2);
        assert_eq!(at(&h, 0, 0), 1.5);
        assert_eq!(at(&h, 2, 3), 2.5);
        assert!(at(&h, 5, 0).is_nan() && at(&h, 1, 1).is_nan() && at(&h, 3, 2).is_nan());
        assert!(h.fit.is_none());
        assert_eq!(s.to_world, Affine2::IDENTITY);
        assert!(
            h.warnings.iter().any(|w| w.contains("grid indices")),
            "{:?}",
            h.warnings
        );
    }

    #[test]
    fn non_integral_steps() {
        let p = temp("half.txt", "10.5 3 1\n11.0 3.25 2\n12.0 3.75 3\n");
        let h = parse(&p).unwrap();
        assert_eq!(
            (h.survey.inline0, h.survey.inline_step, h.survey.n_inline),
            (10.5, 0.5, 4)
        );
        assert_eq!(
            (h.survey.xline0, h.survey.xline_step, h.survey.n_xline),
            (3.0, 0.25, 4)
        );
        assert_eq!(h.holes, 13);
        assert_eq!(at(&h, 3, 3), 3.0);
        let p = temp("tenth.txt", "0.1 0 1\n0.3 0 2\n0.7 1 3\n");
        let h = parse(&p).unwrap();
        assert!((h.survey.inline_step - 0.2).abs() < 1e-9, "{:?}", h.survey);
        assert_eq!(h.survey.n_inline, 4);
        assert_eq!((at(&h, 0, 0), at(&h, 1, 0), at(&h, 3, 1)), (1.0, 2.0, 3.0));
    }

    #[test]
    fn xy_fit_of_rotated_grid_is_exact_and_duplicates_keep_last() {
        let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
        let truth = Affine2 {
            rows: [
                [25.0 * c, -12.5 * s, 612_345.6],
                [25.0 * s, 12.5 * c, 6_078_901.2],
            ],
        };
        let mut text = String::from("X Y Inline Crossline Z\n");
        // Reverse order, inline step 4 starting at 1000, crossline step 1 starting at 7.
        for j in (0..9u32).rev() {
            for i in (0..6u32).rev() {
                let w = truth.apply([i as f64, j as f64]);
                text += &format!(
                    "{:.6} {:.6} {} {} {}\n",
                    w[0],
                    w[1],
                    1000 + 4 * i,
                    7 + j,
                    i * 100 + j
                );
            }
        }
        text += &format!(
            "{} {} 1004 8 -1\n",
            truth.apply([1.0, 1.0])[0],
            truth.apply([1.0, 1.0])[1]
        );
        let p = temp("rotated.txt", &text);
        let h = parse(&p).unwrap();
        assert_eq!(
            (h.survey.n_inline, h.survey.n_xline, h.survey.inline_step),
            (6, 9, 4.0)
        );
        let fit = h.fit.unwrap();
        assert!(fit.max_residual < 1e-5, "{fit:?}");
        for r in 0..2 {
            for k in 0..3 {
                assert!(
                    (h.survey.to_world.rows[r][k] - truth.rows[r][k]).abs() < 1e-5,
                    "{:?}",
                    h.survey.to_world
                );
            }
        }
        assert_eq!(at(&h, 1, 1), -1.0);
        assert_eq!(at(&h, 5, 8), 508.0);
        assert_eq!(h.holes, 0);
        assert!(
            h.warnings.iter().any(|w| w.contains("1 duplicate")),
            "{:?}",
            h.warnings
        );
    }

    #[test]
    fn survey_grid_drops_off_grid_points() {
        let survey = SurveyGrid {
            inline0: 100.0,
            inline_step: 2.0,
            n_inline: 3,
            xline0: 10.0,
            xline_step: 1.0,
            n_xline: 2,
            to_world: Affine2 {
                rows: [[50.0, 0.0, 5.0], [0.0, 25.0, 7.0]],
            },
        };
        let p = temp("survey.txt", "100 10 1\n104 11 2\n106 10 3\n102 10 4\n");
        let opts = HorizonParseOptions {
            survey: Some(survey),
            ..Default::default()
        };
        let h = parse_horizon(&p, &opts).unwrap();
        assert_eq!(h.survey, survey);
        assert_eq!((h.nodes_read, h.dropped, h.holes), (4, 1, 3));
        assert_eq!((at(&h, 0, 0), at(&h, 2, 1), at(&h, 1, 0)), (1.0, 2.0, 4.0));
        assert!(
            h.warnings
                .iter()
                .any(|w| w.contains("dropped 1 of 4") && w.contains("line 3")),
            "{:?}",
            h.warnings
        );
        // Off-node (between inlines) is dropped too.
        let p = temp("survey2.txt", "101 10 1\n100 10 2\n102 11 3\n");
        let h = parse_horizon(&p, &opts).unwrap();
        assert_eq!(h.dropped, 1);
    }

    #[test]
    fn auto_detection_and_forced_formats() {
        let p = temp("grid3.txt", "1 2 3\n4 5 6\n");
        assert_eq!(parse(&p).unwrap().survey.n_xline, 2); // 3 columns → IlXlZ: xlines 2 and 5
        let opts = HorizonParseOptions {
            format: HorizonFormat::Grid,
            ..Default::default()
        };
        let g = parse_horizon(&p, &opts).unwrap();
        assert_eq!((g.survey.n_inline, g.survey.n_xline), (2, 3));
        assert_eq!(at(&g, 1, 0), 4.0);
        let p = temp("grid4.txt", "1 2 3 4\n5 nan 7 8\n");
        let g = parse(&p).unwrap();
        assert_eq!((g.survey.n_inline, g.survey.n_xline, g.holes), (2, 4, 1));
        let opts = HorizonParseOptions {
            format: HorizonFormat::XyIlXlZ,
            ..Default::default()
        };
        let e = parse_horizon(&p, &opts).unwrap_err().to_string();
        assert!(
            e.contains("grid4.txt:1:") && e.contains("expected 5 columns") && e.contains("found 4"),
            "{e}"
        );
    }

    fn err_of(name: &str, text: &str) -> String {
        let p = temp(name, text);
        let e = parse(&p).unwrap_err().to_string();
        assert!(e.contains(name), "{e}");
        assert!(!e.contains('\n'), "{e}");
        e
    }

    #[test]
    fn bad_inputs_are_errors_naming_file_and_line() {
        let e = err_of("bad_token.txt", "# c\n1 2 3\n1 3 abc\n");
        assert!(
            e.contains("bad_token.txt:3:") && e.contains("column 3") && e.contains("\"abc\""),
            "{e}"
        );
        let e = err_of("bad_inline.txt", "1 2 3\nx1 3 4\n");
        assert!(
            e.contains("bad_inline.txt:2:") && e.contains("column 1"),
            "{e}"
        );
        let e = err_of("ragged.txt", "1 2 3 4\n1 2 3 4\n1 2 3\n");
        assert!(
            e.contains("ragged.txt:3:") && e.contains("expected 4") && e.contains("found 3"),
            "{e}"
        );
        let e = err_of("ragged_points.txt", "1 2 3\n1 3 4 5\n");
        assert!(
            e.contains("ragged_points.txt:2:") && e.contains("expected 3") && e.contains("found 4"),
            "{e}"
        );
        let e = err_of("empty.txt", "");
        assert!(e.contains("empty.txt:") && e.contains("no"), "{e}");
        let e = err_of("comments_only.txt", "# a\n\n// b\nX Y Z\n");
        assert!(e.contains("header at line 4"), "{e}");
        let e = err_of("inf.txt", "1 2 3\n1 3 inf\n");
        assert!(e.contains("inf.txt:2:") && e.contains("finite"), "{e}");
        let e = err_of("inf_grid.txt", "1 2 3 4\n1 2 -Infinity 4\n");
        assert!(
            e.contains("inf_grid.txt:2:") && e.contains("column 3"),
            "{e}"
        );
        let e = err_of("nan_inline.txt", "1 2 3\nnan 3 4\n");
        assert!(
            e.contains("nan_inline.txt:2:") && e.contains("inline"),
            "{e}"
        );
        let e = err_of("late_header.txt", "1 2 3\nInline Crossline Z\n");
        assert!(e.contains("late_header.txt:2:"), "{e}");
        let e = err_of("garbage_geometry.txt", "1 1 3\n2 2 3\n100000 3 3\n");
        assert!(e.contains("plausible grid"), "{e}");
        let e = err_of("overflow.txt", "1 2 1e39\n2 2 1\n3 3 1\n");
        assert!(e.contains("overflow.txt:1:"), "{e}");
        // Not UTF-8 in a data line.
        let p = temp("binary.txt", "");
        std::fs::write(&p, b"1 2 3\n1 \xff 3\n").unwrap();
        let e = parse(&p).unwrap_err().to_string();
        assert!(e.contains("binary.txt:2:"), "{e}");
        // A null value that is not a finite number (`--null 1e400` reads as infinity).
        let p = temp("null_inf.txt", "1 2 3\n1 3 4\n");
        for null in [f64::INFINITY, f64::NAN] {
            let opts = HorizonParseOptions {
                null_value: Some(null),
                ..Default::default()
            };
            let e = parse_horizon(&p, &opts).unwrap_err().to_string();
            assert!(e.contains("null_inf.txt") && e.contains("finite"), "{e}");
        }
        // Missing file.
        let e = parse(Path::new("/nonexistent/horizon.dat"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("horizon.dat"), "{e}");
    }

    #[test]
    fn crlf_bom_and_survey_validation() {
        let p = temp(
            "crlf.txt",
            "\u{feff}# c\r\nIL XL Z\r\n1 1 5\r\n1 2 6\r\n2 1 7\r\n",
        );
        let h = parse(&p).unwrap();
        assert_eq!((h.survey.n_inline, h.survey.n_xline, h.holes), (2, 2, 1));
        // Lines ended by CR alone are refused naming the file and line (they had read as
        // one line of nine numbers: a 1 × 9 grid).
        for text in ["1 1 5\r1 2 6\r2 1 7\r", "IL XL Z\n1 1 5\r1 2 6\r2 1 7\r\n"] {
            let cr = temp("cr.txt", text);
            let e = format!("{:#}", parse(&cr).unwrap_err());
            assert!(e.contains("cr.txt:") && e.contains("CR"), "{e}");
        }
        let bad = SurveyGrid {
            inline0: 0.0,
            inline_step: 0.0,
            n_inline: 1,
            xline0: 0.0,
            xline_step: 1.0,
            n_xline: 1,
            to_world: Affine2::IDENTITY,
        };
        let opts = HorizonParseOptions {
            survey: Some(bad),
            ..Default::default()
        };
        assert!(parse_horizon(&p, &opts).is_err());
        let opts = HorizonParseOptions {
            format: HorizonFormat::Grid,
            grid_step: (0.0, 1.0),
            ..Default::default()
        };
        assert!(parse_horizon(&p, &opts).is_err());
    }

    #[test]
    fn gcd_helper() {
        assert_eq!(gcd_f64(12.0, 18.0), 6.0);
        assert_eq!(gcd_f64(0.0, 4.0), 4.0);
        assert!((gcd_f64(0.30000000000000004, 0.2) - 0.1).abs() < 1e-12);
        assert_eq!(gcd_f64(1.5, 0.5), 0.5);
    }
}
