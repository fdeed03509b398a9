//! Colour maps and 1D transfer functions.
//!
//! A transfer function maps a sample value to straight RGBA (colour from a named colour map,
//! opacity from a piecewise-linear curve) with alpha defined per *reference step* (one
//! finest voxel spacing of the volume it colours). The caster uses per-step tables: premultiplied colour with the
//! opacity already corrected for that step, α' = 1 − (1 − α)^(Δs/Δs₀), so no `powf` runs per
//! sample. Empty-space skipping asks [`TransferFunction::max_alpha`] whether any value in a
//! brick's [min, max] can be visible.

use crate::scene::VolumeLayer;

/// A transfer function or colour map that cannot be built, with the reason.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct TfError(pub String);

type Result<T> = std::result::Result<T, TfError>;

macro_rules! bail {
    ($($t:tt)*) => {
        return Err(TfError(format!($($t)*)))
    };
}

/// Entries per table (the GPU caster's tables have the same size).
pub use crate::gpu::TF_SIZE;

/// sRGB-encoded control points of the built-in maps, converted to linear when sampled.
fn map_points(name: &str) -> Option<&'static [[f32; 3]]> {
    const SEISMIC: &[[f32; 3]] = &[
        [0.0, 0.0, 0.3],
        [0.0, 0.25, 1.0],
        [0.95, 0.95, 0.95],
        [1.0, 0.25, 0.0],
        [0.5, 0.0, 0.0],
    ];
    const GREY: &[[f32; 3]] = &[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]];
    // Colour values, not approximations of 1/π (0.318 is a blue component).
    #[allow(clippy::approx_constant)]
    const VIRIDIS: &[[f32; 3]] = &[
        [0.267, 0.005, 0.329],
        [0.283, 0.141, 0.458],
        [0.254, 0.265, 0.530],
        [0.207, 0.372, 0.553],
        [0.164, 0.471, 0.558],
        [0.128, 0.567, 0.551],
        [0.135, 0.659, 0.518],
        [0.267, 0.749, 0.441],
        [0.478, 0.821, 0.318],
        [0.741, 0.873, 0.150],
        [0.993, 0.906, 0.144],
    ];
    const BONE: &[[f32; 3]] = &[
        [0.0, 0.0, 0.0],
        [0.32, 0.32, 0.44],
        [0.65, 0.78, 0.78],
        [1.0, 1.0, 1.0],
    ];
    const HOT: &[[f32; 3]] = &[
        [0.04, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [1.0, 1.0, 1.0],
    ];
    Some(match name {
        "seismic" | "bwr" | "blue-white-red" => SEISMIC,
        "grey" | "gray" => GREY,
        "viridis" => VIRIDIS,
        "bone" => BONE,
        "hot" => HOT,
        _ => return None,
    })
}

/// Names of the built-in colour maps; each also exists reversed as `NAME_r`.
/// `seismic` and `bwr` share the diverging blue-white-red colours (white exactly at the
/// window's middle); `seismic` defaults to opacity rising with |amplitude| ("bright spots"),
/// `bwr` to opaque. `gray` and `blue-white-red` are accepted as other names of `grey` and
/// `bwr`.
pub const COLORMAPS: &[&str] = &["seismic", "bwr", "grey", "viridis", "bone", "hot"];

/// Whether a colour map is diverging (white at the middle of its window), so a signed
/// volume's default window is symmetric about zero.
pub fn is_diverging(name: &str) -> bool {
    matches!(
        name.strip_suffix("_r").unwrap_or(name),
        "seismic" | "bwr" | "blue-white-red"
    )
}

fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// A colour map sampled at `x` in [0, 1] (linear RGB).
#[derive(Clone, Debug)]
pub struct ColorMap {
    points: Vec<[f32; 3]>,
}

impl ColorMap {
    /// A built-in map by name.
    pub fn named(name: &str) -> Result<Self> {
        let (base, reversed) = match name.strip_suffix("_r") {
            Some(b) => (b, true),
            None => (name, false),
        };
        match map_points(base) {
            Some(p) => {
                let mut points: Vec<[f32; 3]> = p.iter().map(|c| c.map(srgb_to_linear)).collect();
                if reversed {
                    points.reverse();
                }
                Ok(ColorMap { points })
            }
            None => bail!(
                "unknown colour map {name:?} (expected one of {}, or one of them reversed as NAME_r)",
                COLORMAPS.join(", ")
            ),
        }
    }

    /// The control points, linear RGB, evenly spaced over [0, 1] (the GPU caster
    /// interpolates them as [`ColorMap::at`] does).
    pub fn points(&self) -> &[[f32; 3]] {
        &self.points
    }

    /// Linear RGB at `x` (clamped to [0, 1]).
    pub fn at(&self, x: f32) -> [f32; 3] {
        let n = self.points.len();
        let s = x.clamp(0.0, 1.0) * (n - 1) as f32;
        let i = (s as usize).min(n - 2);
        let f = s - i as f32;
        let (a, b) = (self.points[i], self.points[i + 1]);
        [0, 1, 2].map(|k| a[k] + f * (b[k] - a[k]))
    }
}

/// Checks a value window (`window = [lo, hi]` of a volume): two finite values `lo < hi`
/// that stay two distinct finite values in f32. Shared by [`TransferFunction::from_layer`]
/// and the scene's own checks, so a bad window in a scene file names its line.
pub fn check_window([lo, hi]: [f64; 2]) -> Result<()> {
    if !(lo.is_finite() && hi.is_finite() && hi > lo) {
        bail!("window must be two finite values lo < hi, got [{lo}, {hi}]");
    }
    // The casters map values in f32: the window must stay two distinct finite values
    // there (1e8 and 1e8 + 1 are one f32; ±1e40 are infinite), or every position is NaN.
    let (lo32, hi32) = (lo as f32, hi as f32);
    if !(lo32.is_finite() && hi32.is_finite() && hi32 > lo32) {
        bail!(
            "window [{lo}, {hi}] is not two distinct finite values in f32 \
             (the samples' precision): widen it, or keep it within ±3.4e38"
        );
    }
    // Nor so narrow that the value → table-position map overflows f32 (a width under
    // about 1e-35): every value would then map to an end of the table, and 0 to NaN.
    let scale = (TF_SIZE - 1) as f64 / (hi32 as f64 - lo32 as f64);
    let (s32, o32) = (scale as f32, (-(lo32 as f64) * scale) as f32);
    if !(s32.is_finite() && o32.is_finite()) {
        bail!(
            "window [{lo}, {hi}] is too narrow for f32 positions (width {:e}): widen it",
            hi - lo
        );
    }
    Ok(())
}

/// Checks an opacity curve (`opacity_points` of a volume): at least one `[position, alpha]`
/// pair, finite positions that do not decrease, alphas in [0, 1]. Shared as
/// [`check_window`] is.
pub fn check_opacity_points(p: &[[f64; 2]]) -> Result<()> {
    if p.is_empty() {
        bail!("opacity_points must hold at least one [position, alpha] pair");
    }
    if let Some(q) = p.iter().find(|q| !q[0].is_finite()) {
        bail!("opacity_points positions must be finite, got {}", q[0]);
    }
    for w in p.windows(2) {
        if w[1][0] < w[0][0] {
            bail!(
                "opacity_points positions must not decrease ({} after {})",
                w[1][0],
                w[0][0]
            );
        }
    }
    if let Some(q) = p.iter().find(|q| !(0.0..=1.0).contains(&q[1])) {
        bail!("opacity_points alphas must lie in [0, 1], got {}", q[1]);
    }
    Ok(())
}

/// A volume's transfer function over its value window.
#[derive(Clone, Debug)]
pub struct TransferFunction {
    /// Value at table entry 0.
    pub lo: f32,
    /// Value at the last entry.
    pub hi: f32,
    /// Straight RGBA, alpha per reference step.
    pub table: Vec<[f32; 4]>,
    /// `block_max[b]`: largest alpha among the `BLOCK` (16) entries of block `b` (the last
    /// block may be shorter); `max_alpha` takes whole blocks from it.
    block_max: Vec<f32>,
}

const BLOCK: usize = 16;

impl TransferFunction {
    /// Builds the transfer function of a volume layer; `range` is the window used when the
    /// layer sets none (the store's value range, or a seismic clip; see the worker's
    /// `dataset::Volume::open`).
    pub fn from_layer(layer: &VolumeLayer, range: [f64; 2]) -> Result<Self> {
        let cmap = ColorMap::named(&layer.colormap)?;
        let [lo, hi] = layer.window.unwrap_or(range);
        check_window([lo, hi]).map_err(|e| TfError(format!("volume {e}")))?;
        if !(layer.opacity >= 0.0 && layer.opacity.is_finite()) {
            bail!("volume opacity must be >= 0, got {}", layer.opacity);
        }
        let points: Vec<[f64; 2]> = match &layer.opacity_points {
            Some(p) => {
                check_opacity_points(p)?;
                p.clone()
            }
            // Opaque blue-white-red.
            None if matches!(
                layer.colormap.strip_suffix("_r").unwrap_or(&layer.colormap),
                "bwr" | "blue-white-red"
            ) =>
            {
                vec![[0.0, 1.0], [1.0, 1.0]]
            }
            None if layer.colormap.strip_suffix("_r").unwrap_or(&layer.colormap) == "seismic" => {
                vec![
                    [0.0, 1.0],
                    [0.35, 0.08],
                    [0.45, 0.0],
                    [0.55, 0.0],
                    [0.65, 0.08],
                    [1.0, 1.0],
                ]
            }
            None => vec![[0.0, 0.0], [0.1, 0.0], [1.0, 0.5]],
        };
        let curve = |x: f64| -> f64 {
            if x <= points[0][0] {
                return points[0][1];
            }
            for w in points.windows(2) {
                if x <= w[1][0] {
                    let span = w[1][0] - w[0][0];
                    let f = if span > 0.0 {
                        (x - w[0][0]) / span
                    } else {
                        1.0
                    };
                    return w[0][1] + f * (w[1][1] - w[0][1]);
                }
            }
            points[points.len() - 1][1]
        };
        let table: Vec<[f32; 4]> = (0..TF_SIZE)
            .map(|i| {
                let x = i as f64 / (TF_SIZE - 1) as f64;
                let c = cmap.at(x as f32);
                let a = (curve(x) * layer.opacity).clamp(0.0, 1.0) as f32;
                [c[0], c[1], c[2], a]
            })
            .collect();
        Ok(Self::from_table(lo as f32, hi as f32, table))
    }

    /// From an explicit straight-RGBA table (at least two entries).
    pub fn from_table(lo: f32, hi: f32, table: Vec<[f32; 4]>) -> Self {
        assert!(table.len() >= 2);
        let block_max = table
            .chunks(BLOCK)
            .map(|c| c.iter().map(|e| e[3]).fold(0.0, f32::max))
            .collect();
        TransferFunction {
            lo,
            hi,
            table,
            block_max,
        }
    }

    /// Straight RGBA at value `v` (clamped to the window), interpolated between entries as
    /// the step tables are; NaN (no data) gives NaN.
    pub fn straight(&self, v: f32) -> [f32; 4] {
        if v.is_nan() {
            return [f32::NAN; 4];
        }
        // The step tables' value → position map, operation for operation (the GPU caster
        // evaluates the same expression).
        let n = (self.table.len() - 1) as f32;
        let (scale, offset) = self.position_map();
        let x = (v * scale + offset).clamp(0.0, n);
        let i = (x as usize).min(self.table.len() - 2);
        let f = x - i as f32;
        let (a, b) = (self.table[i], self.table[i + 1]);
        [0, 1, 2, 3].map(|k| a[k] + f * (b[k] - a[k]))
    }

    /// Whether a page with value bounds `[min, max]` contributes nothing: no valid value
    /// (NaN bounds), or (with empty-space skipping) only values this function makes
    /// transparent. Both casters skip such bricks and the decomposition weighs them down.
    pub fn page_transparent(&self, b: [f32; 2], skipping: bool) -> bool {
        if skipping {
            self.max_alpha(b[0], b[1]) <= 0.0
        } else {
            !(b[0] <= b[1])
        }
    }

    /// Largest alpha any value in `[vmin, vmax]` can map to (interpolation included).
    ///
    /// The entries are exactly those the casters' own lookups read: the position is their
    /// f32 `v · scale + offset` ([`position_map`](Self::position_map)), rounded as the CPU
    /// rounds it (product, then sum) or as a GPU may (one fused multiply-add); either is
    /// monotonic in `v`, so the range's ends bound every value's entries. Positions taken
    /// exactly in f64 had left out the neighbour a lookup a hair off an entry blends in:
    /// 255 under the window [0, 255] is entry 1023 exactly, but 1022.99994 in f32, which
    /// reads 6·10⁻⁵ of entry 1022, so a macrocell of 255s under a function clear only at
    /// 255 was skipped while its samples were not clear.
    pub fn max_alpha(&self, vmin: f32, vmax: f32) -> f32 {
        if !(vmin <= vmax) {
            return 0.0; // empty or NaN range: no valid sample
        }
        let n = (self.table.len() - 1) as f32;
        let (scale, offset) = self.position_map();
        let (lo, hi) = {
            let at = |v: f32| {
                let (a, b) = (v * scale + offset, v.mul_add(scale, offset));
                (a.min(b), a.max(b))
            };
            (at(vmin).0, at(vmax).1)
        };
        let i0 = lo.clamp(0.0, n).floor() as usize;
        let i1 = (hi.clamp(0.0, n).ceil() as usize).min(self.table.len() - 1);
        let mut m = 0.0f32;
        let mut i = i0;
        while i <= i1 {
            if i.is_multiple_of(BLOCK) && i + BLOCK - 1 <= i1 {
                m = m.max(self.block_max[i / BLOCK]);
                i += BLOCK;
            } else {
                m = m.max(self.table[i][3]);
                i += 1;
            }
        }
        m
    }

    /// The lookup table for a step `exponent` = Δs/Δs₀: premultiplied colour with corrected
    /// alpha, as `[r, g, b, a]` entries plus the scale/offset that maps values to positions.
    pub fn step_table(&self, exponent: f32) -> StepTable {
        let entries = self
            .table
            .iter()
            .map(|e| {
                let a = if exponent == 1.0 {
                    e[3]
                } else {
                    corrected_alpha(e[3], exponent)
                };
                [e[0] * a, e[1] * a, e[2] * a, a]
            })
            .collect();
        let (scale, offset) = self.position_map();
        StepTable {
            entries,
            scale,
            offset,
            last: (self.table.len() - 1) as f32,
        }
    }

    /// The value → table position map `v·scale + offset`, computed in f64 so that windows
    /// wider than `f32::MAX` (values near the f32 limits) do not overflow to a zero scale.
    pub fn position_map(&self) -> (f32, f32) {
        let n = (self.table.len() - 1) as f64;
        let scale = n / (self.hi as f64 - self.lo as f64);
        (scale as f32, (-(self.lo as f64) * scale) as f32)
    }
}

/// Opacity `a` per reference step corrected for a step of `exponent` reference steps,
/// `1 − (1 − a)^exponent`, as `−expm1(exponent · ln1p(−a))` in f64: the f32 form loses all
/// precision when `1 − a` rounds to 1 (a = 1e-7 came out 19 % high at exponent 1000) or
/// when the power is close to 1 (tiny exponents).
pub fn corrected_alpha(a: f32, exponent: f32) -> f32 {
    let a = (a as f64).clamp(0.0, 1.0);
    if a >= 1.0 {
        return 1.0;
    }
    (-((exponent as f64) * (-a).ln_1p()).exp_m1()) as f32
}

/// Entries per axis of a pre-integrated table.
pub const PREINT_SIZE: usize = 256;

impl TransferFunction {
    /// The pre-integrated table for a step of `exponent` reference steps (seed 001, Engel et
    /// al. 2001): entry `(f, b)` is the premultiplied RGBA of a segment whose value runs
    /// linearly from table position `f` to `b`, composited front to back in f64 over one
    /// sub-step per transfer-function entry the segment crosses (at least 8, at most 2048),
    /// each opacity-corrected to its length. Over a constant value it equals the step table's
    /// entry; over a thin opacity peak between two samples it keeps what a point sample
    /// misses.
    pub fn preintegrated_table(&self, exponent: f32) -> PreintTable {
        let n = PREINT_SIZE;
        let m = (self.table.len() - 1) as f64;
        // Positions in table units of the pre-integrated axes.
        let (scale, offset) = self.position_map();
        let r = (n - 1) as f64 / m;
        PreintTable {
            entries: self.segments(exponent as f64),
            half_entries: self.segments(exponent as f64 * 0.5),
            scale: (scale as f64 * r) as f32,
            offset: (offset as f64 * r) as f32,
            last: (n - 1) as f32,
        }
    }

    /// The `PREINT_SIZE`² segment entries for a segment of `e` reference steps.
    fn segments(&self, e: f64) -> Vec<[f32; 4]> {
        let n = PREINT_SIZE;
        let m = (self.table.len() - 1) as f64;
        let mut entries = vec![[0f32; 4]; n * n];
        let straight = |x: f64| -> [f64; 4] {
            let p = (x * m).clamp(0.0, m);
            let i = (p as usize).min(self.table.len() - 2);
            let f = p - i as f64;
            let (a, b) = (self.table[i], self.table[i + 1]);
            [0, 1, 2, 3].map(|k| a[k] as f64 + f * (b[k] as f64 - a[k] as f64))
        };
        for (fi, row) in entries.chunks_mut(n).enumerate() {
            let xf = fi as f64 / (n - 1) as f64;
            for (bi, out) in row.iter_mut().enumerate() {
                let xb = bi as f64 / (n - 1) as f64;
                let k = (((xb - xf).abs() * m).ceil() as usize).clamp(8, 2048);
                let mut c = [0.0f64; 3];
                let mut t = 1.0f64; // transmittance so far
                for j in 0..k {
                    let u = (j as f64 + 0.5) / k as f64;
                    let s = straight(xf + u * (xb - xf));
                    // Sub-step opacity: 1 − (1 − α)^(e/k), in the expm1/ln1p form. An
                    // opaque entry is opaque over any part of a step (as the step table's
                    // is): clamped short of 1, k sub-steps of a short step had multiplied
                    // back to 1 − 1e-7^e, 0.55 at e = 0.05.
                    let a = if s[3] >= 1.0 {
                        1.0
                    } else {
                        -((e / k as f64) * (-s[3].max(0.0)).ln_1p()).exp_m1()
                    };
                    for q in 0..3 {
                        c[q] += t * a * s[q];
                    }
                    t *= 1.0 - a;
                }
                *out = [c[0] as f32, c[1] as f32, c[2] as f32, (1.0 - t) as f32];
            }
        }
        entries
    }
}

/// A pre-integrated lookup: premultiplied RGBA of a segment from a front value to a back
/// value, `PREINT_SIZE`² entries, front value major.
#[derive(Clone, Debug)]
pub struct PreintTable {
    /// Premultiplied RGBA, `entries[f · PREINT_SIZE + b]`.
    pub entries: Vec<[f32; 4]>,
    /// Value → position scale.
    pub scale: f32,
    /// Value → position offset.
    pub offset: f32,
    /// Last position (`PREINT_SIZE − 1`).
    pub last: f32,
    /// The same for segments half as long: a span of samples covers half a step before
    /// its first sample and half a step after its last, as point samples would.
    pub half_entries: Vec<[f32; 4]>,
}

impl PreintTable {
    /// Premultiplied RGBA of the segment from value `front` to value `back` (bilinear
    /// between entries).
    #[inline]
    pub fn lookup(&self, front: f32, back: f32) -> [f32; 4] {
        self.lookup_in(&self.entries, front, back)
    }

    /// [`lookup`](Self::lookup) for a segment half a step long.
    #[inline]
    pub fn lookup_half(&self, front: f32, back: f32) -> [f32; 4] {
        self.lookup_in(&self.half_entries, front, back)
    }

    /// A segment whose values leave the window runs partly at the window's edge value
    /// (the transfer function is constant beyond it): its pieces inside and outside are
    /// composited in path order, each the table's segment scaled to its share of the step
    /// (clamping both ends into the window had integrated the inside piece over the whole
    /// step and dropped the rest: from 0 to 10 over a window [0, 1] with opacity rising
    /// to 1, 0.63 instead of opaque).
    #[inline(always)]
    fn lookup_in(&self, e: &[[f32; 4]], front: f32, back: f32) -> [f32; 4] {
        let pf = front * self.scale + self.offset;
        let pb = back * self.scale + self.offset;
        let last = self.last;
        if (0.0..=last).contains(&pf) && (0.0..=last).contains(&pb) || !(pf - pb).is_finite() {
            return self.bilinear(e, pf, pb);
        }
        // Cut the path pf → pb at the window's edges, front to back.
        let mut cuts = [pf, 0.0, 0.0, pb];
        let mut n = 1;
        let (lo, hi) = if pf <= pb { (pf, pb) } else { (pb, pf) };
        let mut edges = [0.0, last];
        if pf > pb {
            edges.swap(0, 1);
        }
        for x in edges {
            if lo < x && x < hi {
                cuts[n] = x;
                n += 1;
            }
        }
        cuts[n] = pb;
        let len = hi - lo;
        let mut acc = [0.0f32; 4];
        for k in 0..n {
            let (x1, x2) = (cuts[k], cuts[k + 1]);
            if x1 == x2 {
                continue;
            }
            let w = if len > 0.0 {
                (x2 - x1).abs() / len
            } else {
                1.0
            };
            let piece = scaled(self.bilinear(e, x1, x2), w);
            let t = 1.0 - acc[3];
            for c in 0..4 {
                acc[c] += t * piece[c];
            }
        }
        acc
    }

    /// The table between entries (positions clamped into it).
    #[inline(always)]
    fn bilinear(&self, e: &[[f32; 4]], pf: f32, pb: f32) -> [f32; 4] {
        let n = PREINT_SIZE;
        let pf = pf.clamp(0.0, self.last);
        let pb = pb.clamp(0.0, self.last);
        let i = (pf as usize).min(n - 2);
        let j = (pb as usize).min(n - 2);
        let (u, v) = (pf - i as f32, pb - j as f32);
        let (a, b, c, d) = (
            e[i * n + j],
            e[i * n + j + 1],
            e[(i + 1) * n + j],
            e[(i + 1) * n + j + 1],
        );
        [0, 1, 2, 3].map(|k| {
            let top = a[k] + v * (b[k] - a[k]);
            let bottom = c[k] + v * (d[k] - c[k]);
            top + u * (bottom - top)
        })
    }
}

/// A premultiplied segment's RGBA over a share `w` of its length, its value path the same:
/// the optical depth scales with the length, so alpha is `1 − (1 − α)^w` exactly, and the
/// colour keeps its ratio to alpha (exact for a constant value). An opaque segment stays
/// opaque. (In f32 with `powf`, as the GPU caster computes it.)
#[inline]
fn scaled(rgba: [f32; 4], w: f32) -> [f32; 4] {
    let a = rgba[3];
    if a >= 1.0 || w >= 1.0 {
        return rgba;
    }
    if a <= 0.0 || w <= 0.0 {
        return [0.0; 4];
    }
    let aw = 1.0 - (1.0 - a).powf(w);
    let k = aw / a;
    [rgba[0] * k, rgba[1] * k, rgba[2] * k, aw]
}

/// A premultiplied, step-corrected lookup table.
#[derive(Clone, Debug)]
pub struct StepTable {
    /// Premultiplied RGBA entries.
    pub entries: Vec<[f32; 4]>,
    /// Value → position scale.
    pub scale: f32,
    /// Value → position offset.
    pub offset: f32,
    /// Last position (entries − 1).
    pub last: f32,
}

impl StepTable {
    /// Premultiplied RGBA of a value (linear interpolation between entries).
    #[inline(always)]
    pub fn lookup(&self, v: f32) -> [f32; 4] {
        let s = (v * self.scale + self.offset).clamp(0.0, self.last);
        let i = (s as usize).min(self.entries.len() - 2);
        let f = s - i as f32;
        // SAFETY: tables have at least two entries (`from_table` asserts it) and
        // i <= len − 2, so i and i + 1 are in bounds.
        let (a, b) = unsafe {
            (
                *self.entries.get_unchecked(i),
                *self.entries.get_unchecked(i + 1),
            )
        };
        [
            a[0] + f * (b[0] - a[0]),
            a[1] + f * (b[1] - a[1]),
            a[2] + f * (b[2] - a[2]),
            a[3] + f * (b[3] - a[3]),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn preintegrated_constant_segments_match_the_step_table() {
        let tf = TransferFunction::from_layer(&layer("seismic"), [-1.0, 1.0]).unwrap();
        for e in [0.25f32, 1.0, 4.0] {
            let pre = tf.preintegrated_table(e);
            let step = tf.step_table(e);
            for i in 0..=20 {
                let v = -1.0 + i as f32 * 0.1;
                let (p, s) = (pre.lookup(v, v), step.lookup(v));
                for k in 0..4 {
                    // Bilinear over 256 entries against linear over 1024: the curve's
                    // kinks fall between entries, so allow the interpolation difference.
                    assert!((p[k] - s[k]).abs() < 2e-2, "e {e} v {v}: {p:?} vs {s:?}");
                }
            }
        }
    }

    #[test]
    fn a_window_that_collapses_in_f32_is_refused() {
        // Distinct values, but too close, too far apart, or too narrow a window for the
        // position map (1023/1e-40 overflows f32: every value went to an end, 0 to NaN).
        for w in [
            [1e8, 1e8 + 1.0],
            [-1e40, 1e40],
            [0.0, 1e-40],
            [1e-38, 1.5e-38],
        ] {
            let mut l = layer("grey");
            l.window = Some(w);
            let e = TransferFunction::from_layer(&l, [0.0, 1.0]).unwrap_err();
            assert!(e.to_string().contains("f32"), "{w:?}: {e}");
        }
        let mut l = layer("grey");
        l.window = Some([0.0, 1e-30]);
        let tf = TransferFunction::from_layer(&l, [0.0, 1.0]).unwrap();
        assert!(tf.step_table(1.0).lookup(0.0).iter().all(|v| v.is_finite()));
        let mut l = layer("grey");
        l.window = Some([1e8, 1e8 + 64.0]);
        let tf = TransferFunction::from_layer(&l, [0.0, 1.0]).unwrap();
        assert!(tf
            .step_table(1.0)
            .lookup(1e8 + 32.0)
            .iter()
            .all(|v| v.is_finite()));
    }

    /// A segment whose values run past the window spends that part at the edge's entry (the
    /// transfer function is constant beyond it): the lookup agrees with a fine integration
    /// of the clamped path. Both ends clamped into the window, a segment from 0 to 10 had
    /// integrated 0 → 1 over the whole step and dropped the 90 % of it at the top entry.
    #[test]
    fn a_segment_that_leaves_the_window_spends_that_part_at_the_edge_value() {
        let table: Vec<[f32; 4]> = (0..TF_SIZE)
            .map(|i| {
                let x = i as f32 / (TF_SIZE - 1) as f32;
                [0.5 * x * x, 0.5 * x, 0.5 * x * (1.0 - x), 0.5 * x]
            })
            .collect();
        let tf = TransferFunction::from_table(0.0, 1.0, table.clone());
        // Front to back over k sub-steps of the clamped linear path, premultiplied.
        let brute = |f: f64, b: f64, e: f64| {
            let k = 20_000;
            let m = (TF_SIZE - 1) as f64;
            let (mut c, mut t) = ([0.0f64; 3], 1.0f64);
            for j in 0..k {
                let x = (f + (j as f64 + 0.5) / k as f64 * (b - f)).clamp(0.0, 1.0) * m;
                let i = (x as usize).min(TF_SIZE - 2);
                let u = x - i as f64;
                let s = [0, 1, 2, 3].map(|q| {
                    table[i][q] as f64 + u * (table[i + 1][q] as f64 - table[i][q] as f64)
                });
                let a = 1.0 - (1.0 - s[3]).powf(e / k as f64);
                for q in 0..3 {
                    c[q] += t * a * s[q];
                }
                t *= 1.0 - a;
            }
            [c[0], c[1], c[2], 1.0 - t]
        };
        for e in [1.0f32, 0.5] {
            let pre = tf.preintegrated_table(e);
            for (f, b) in [
                (0.0, 10.0),
                (10.0, 0.0),
                (0.5, 3.0),
                (-2.0, 0.5),
                (-1.0, 2.0),
                (2.0, -1.0),
                (1.5, 4.0),
                (-3.0, -1.0),
                (0.2, 0.7),
            ] {
                let got = pre.lookup(f as f32, b as f32);
                let want = brute(f, b, e as f64);
                for q in 0..4 {
                    assert!(
                        (got[q] as f64 - want[q]).abs() < 4e-3,
                        "e {e}, {f} → {b}: {got:?}, want {want:?}"
                    );
                }
            }
        }
    }

    /// Over an opaque entry a segment is opaque, however short (the step table's entry is
    /// 1 for any exponent): half steps and steps of 1/8 had come out 0.867 and 0.982.
    #[test]
    fn an_opaque_entry_is_opaque_over_any_part_of_a_step() {
        let tf = TransferFunction::from_table(0.0, 1.0, vec![[1.0, 1.0, 1.0, 1.0]; 1024]);
        for e in [0.05f32, 0.125, 0.5, 1.0] {
            let pre = tf.preintegrated_table(e);
            assert!((pre.lookup(0.5, 0.5)[3] - 1.0).abs() < 1e-6, "e {e}");
            assert!((pre.lookup_half(0.5, 0.5)[3] - 1.0).abs() < 1e-6, "e {e}");
            assert_eq!(tf.step_table(e).lookup(0.5)[3], 1.0);
        }
    }

    #[test]
    fn preintegration_keeps_a_thin_peak_between_samples() {
        // Opacity 0 everywhere but a spike at the window's middle: samples at -1 and +1 see
        // nothing; the segment between them crosses the spike.
        let mut table = vec![[1.0, 1.0, 1.0, 0.0]; 1024];
        table[511] = [1.0, 0.0, 0.0, 0.9];
        table[512] = [1.0, 0.0, 0.0, 0.9];
        let tf = TransferFunction::from_table(-1.0, 1.0, table);
        assert_eq!(tf.step_table(1.0).lookup(-1.0)[3], 0.0);
        let pre = tf.preintegrated_table(1.0);
        let a = pre.lookup(-1.0, 1.0)[3];
        // About two entries of 1023 at alpha 0.9 over one step: 1 − 0.1^(2/1023) ≈ 4.5e-3.
        assert!(a > 2e-3 && a < 8e-3, "{a}");
        // Front to back and back to front cross the same spike.
        assert!((pre.lookup(1.0, -1.0)[3] - a).abs() < 1e-6);
        // Colour is premultiplied: never above alpha.
        for e in &pre.entries {
            assert!(e[0] <= e[3] + 1e-6 && e[3] <= 1.0 && e[3] >= 0.0);
        }
    }

    fn layer(map: &str) -> VolumeLayer {
        VolumeLayer {
            store: "x".into(),
            colormap: map.into(),
            window: Some([-1.0, 1.0]),
            opacity: 1.0,
            opacity_points: None,
            slices: Vec::new(),
        }
    }

    #[test]
    fn reversed_and_opaque_diverging_maps() {
        let m = ColorMap::named("viridis").unwrap();
        let r = ColorMap::named("viridis_r").unwrap();
        for i in 0..=10 {
            let x = i as f32 / 10.0;
            let (a, b) = (m.at(x), r.at(1.0 - x));
            for k in 0..3 {
                assert!((a[k] - b[k]).abs() < 1e-6, "{x}: {a:?} vs {b:?}");
            }
        }
        // bwr: the seismic colours, white exactly at zero, opaque everywhere.
        let tf = TransferFunction::from_layer(&layer("bwr"), [-1.0, 1.0]).unwrap();
        let mid = tf.straight(0.0);
        assert!(mid[0] > 0.85 && (mid[0] - mid[2]).abs() < 1e-6, "{mid:?}");
        for v in [-1.0f32, -0.3, 0.0, 0.4, 1.0] {
            assert_eq!(tf.straight(v)[3], 1.0, "{v}");
        }
        let lo = tf.straight(-1.0);
        assert!(lo[2] > lo[0], "negative is blue: {lo:?}");
        let rev = TransferFunction::from_layer(&layer("bwr_r"), [-1.0, 1.0]).unwrap();
        assert!(
            rev.straight(-1.0)[0] > rev.straight(-1.0)[2],
            "reversed: negative is red"
        );
        // seismic_r keeps the bright-spot opacity.
        let s = TransferFunction::from_layer(&layer("seismic_r"), [-1.0, 1.0]).unwrap();
        assert!(s.straight(0.0)[3] < 0.01 && s.straight(1.0)[3] > 0.99);
        assert!(is_diverging("seismic_r") && is_diverging("bwr") && !is_diverging("grey"));
        let e = ColorMap::named("nope_r").unwrap_err().to_string();
        assert!(e.contains("NAME_r") && e.contains("bwr"), "{e}");
    }

    #[test]
    fn seismic_is_transparent_near_zero_and_opaque_at_extremes() {
        let tf = TransferFunction::from_layer(&layer("seismic"), [0.0, 1.0]).unwrap();
        assert_eq!(tf.max_alpha(-0.05, 0.05), 0.0);
        assert!(tf.max_alpha(-0.05, 0.5) > 0.0);
        assert_eq!(tf.max_alpha(0.99, 5.0), 1.0);
        assert_eq!(tf.max_alpha(f32::NAN, f32::NAN), 0.0);
    }

    #[test]
    fn max_alpha_bounds_every_lookup() {
        let tf = TransferFunction::from_layer(&layer("grey"), [0.0, 1.0]).unwrap();
        let t = tf.step_table(1.0);
        for k in 0..200 {
            let a = -1.2 + k as f32 * 0.011;
            let b = a + 0.37;
            let m = tf.max_alpha(a, b);
            for j in 0..=20 {
                let v = a + (b - a) * j as f32 / 20.0;
                assert!(t.lookup(v)[3] <= m + 1e-7, "{a} {b} {v}");
            }
        }
    }

    /// Values that land on an entry exactly in f64 but a hair off it in the lookup's f32
    /// (the window's top under [0, 255], [0, 100], [−128, 127], [1000, 1100]) are bounded
    /// with the entry the lookup blends in; a function clear only at the window's top is
    /// not clear there.
    #[test]
    fn max_alpha_bounds_lookups_that_round_off_an_entry() {
        for (lo, hi) in [
            (0.0f32, 255.0f32),
            (0.0, 100.0),
            (-128.0, 127.0),
            (1000.0, 1100.0),
        ] {
            let mut table = vec![[1.0f32, 1.0, 1.0, 0.5]; TF_SIZE];
            table[TF_SIZE - 1][3] = 0.0;
            let tf = TransferFunction::from_table(lo, hi, table);
            let got = tf.step_table(1.0).lookup(hi)[3];
            assert!(
                got <= tf.max_alpha(hi, hi),
                "[{lo}, {hi}]: the lookup of {hi} gives alpha {got}, max_alpha {}",
                tf.max_alpha(hi, hi)
            );
        }
        // Away from entries nothing is taken in: a range inside the clear end stays clear.
        let mut table = vec![[0.0f32; 4]; TF_SIZE];
        table[0][3] = 1.0;
        let tf = TransferFunction::from_table(0.0, 1023.0, table);
        assert_eq!(tf.max_alpha(1.5, 1023.0), 0.0);
        assert!(tf.max_alpha(0.9, 1023.0) > 0.0);
        // Values clamped to an end read that end's entry alone: a ramp from the window's
        // bottom is clear below it, and one falling to its top clear above it.
        let mut table = vec![[0.0f32; 4]; TF_SIZE];
        table[1][3] = 1.0;
        table[TF_SIZE - 2][3] = 1.0;
        let tf = TransferFunction::from_table(0.0, 1023.0, table);
        assert_eq!(tf.max_alpha(-50.0, 0.0), 0.0);
        assert_eq!(tf.max_alpha(1023.0, 5000.0), 0.0);
        // Every entry a lookup reads with a weight, rounded as the CPU rounds (product, then
        // sum) or fused as a GPU may, is bounded, near zero and far from it (products of
        // 2^17 and 2^25, where half an ulp is 1/256 and more).
        for (lo, hi) in [
            (0.0f32, 255.0f32),
            (5000.0, 5050.0),
            (-1.0e6, -1.0e6 + 10.0),
        ] {
            let probe = TransferFunction::from_table(lo, hi, vec![[0.0; 4]; TF_SIZE]);
            let (scale, offset) = probe.position_map();
            let n = (TF_SIZE - 1) as f32;
            for j in 0..400 {
                let v = lo + (hi - lo) * j as f32 / 399.0;
                for x in [v * scale + offset, v.mul_add(scale, offset)] {
                    let x = x.clamp(0.0, n);
                    let i = (x as usize).min(TF_SIZE - 2);
                    let weighted = [(i, x - (i as f32) < 1.0), (i + 1, x > i as f32)];
                    for (k, _) in weighted.into_iter().filter(|&(_, w)| w) {
                        let mut table = vec![[0.0f32; 4]; TF_SIZE];
                        table[k][3] = 1.0;
                        let tf = TransferFunction::from_table(lo, hi, table);
                        assert!(
                            tf.max_alpha(v, v) > 0.0,
                            "[{lo}, {hi}]: {v} reads entry {k} at {x}, max_alpha leaves it out"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn step_correction_matches_formula() {
        let tf = TransferFunction::from_table(0.0, 1.0, vec![[1.0, 1.0, 1.0, 0.3]; 4]);
        let t = tf.step_table(2.5);
        let want = 1.0 - 0.7f32.powf(2.5);
        assert!((t.lookup(0.5)[3] - want).abs() < 1e-6);
        assert!((t.lookup(0.5)[0] - want).abs() < 1e-6);
    }

    #[test]
    fn unknown_map_is_an_error() {
        assert!(TransferFunction::from_layer(&layer("rainbow"), [0.0, 1.0]).is_err());
    }
}
