//! World placement in `f64`: affine transforms and the lateral survey grid.
//!
//! Survey coordinates are projected metres (UTM northings reach 6·10⁶ m); `f32` has a
//! 0.5 m ulp there, so every transform that can carry them is `f64`. Renderers subtract a
//! camera-relative origin in `f64` before converting to `f32`.

use serde::{Deserialize, Serialize};

/// A 3D affine map `p ↦ M·p + t`, stored as three rows `[m0, m1, m2, t]`.
///
/// Page stores use it to map sample index space `(i, j, k)` (level 0) to world `(x, y, z)`.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Affine3 {
    /// Rows of `[M | t]`.
    pub rows: [[f64; 4]; 3],
}

impl Default for Affine3 {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Affine3 {
    /// The identity map.
    pub const IDENTITY: Affine3 = Affine3 {
        rows: [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ],
    };

    /// Axis-aligned scale and offset.
    pub fn scale_offset(scale: [f64; 3], offset: [f64; 3]) -> Self {
        let mut rows = [[0.0; 4]; 3];
        for a in 0..3 {
            rows[a][a] = scale[a];
            rows[a][3] = offset[a];
        }
        Affine3 { rows }
    }
    /// Lateral placement from a survey grid's `(i, j) → (x, y)` map, and `z = dz·k + z0`.
    pub fn from_lateral(lateral: &Affine2, dz: f64, z0: f64) -> Self {
        let w = lateral.rows;
        Affine3 {
            rows: [
                [w[0][0], w[0][1], 0.0, w[0][2]],
                [w[1][0], w[1][1], 0.0, w[1][2]],
                [0.0, 0.0, dz, z0],
            ],
        }
    }
    /// Applies the map.
    pub fn apply(&self, p: [f64; 3]) -> [f64; 3] {
        self.rows
            .map(|r| r[0] * p[0] + r[1] * p[1] + r[2] * p[2] + r[3])
    }
    /// Whether every coefficient is finite.
    pub fn is_finite(&self) -> bool {
        self.rows.iter().flatten().all(|v| v.is_finite())
    }

    /// The inverse map (f64), or `None` if it is singular or nearly so: its determinant
    /// under 1e-12 of the product of its columns' lengths (a test of shape, whatever the
    /// scale: a 1e-15 determinant of unit columns is singular, one of 1e-5 columns is not),
    /// or an inverse that does not come out finite.
    pub fn inverse(&self) -> Option<Affine3> {
        let a = self;
        let m = |r: usize, c: usize| a.rows[r][c];
        let det = m(0, 0) * (m(1, 1) * m(2, 2) - m(1, 2) * m(2, 1))
            - m(0, 1) * (m(1, 0) * m(2, 2) - m(1, 2) * m(2, 0))
            + m(0, 2) * (m(1, 0) * m(2, 1) - m(1, 1) * m(2, 0));
        let norms: f64 = (0..3)
            .map(|c| (0..3).map(|r| m(r, c) * m(r, c)).sum::<f64>().sqrt())
            .product();
        if !(det.is_finite() && norms.is_finite() && det.abs() > 1e-12 * norms) {
            return None;
        }
        let inv = [
            [
                (m(1, 1) * m(2, 2) - m(1, 2) * m(2, 1)) / det,
                (m(0, 2) * m(2, 1) - m(0, 1) * m(2, 2)) / det,
                (m(0, 1) * m(1, 2) - m(0, 2) * m(1, 1)) / det,
            ],
            [
                (m(1, 2) * m(2, 0) - m(1, 0) * m(2, 2)) / det,
                (m(0, 0) * m(2, 2) - m(0, 2) * m(2, 0)) / det,
                (m(0, 2) * m(1, 0) - m(0, 0) * m(1, 2)) / det,
            ],
            [
                (m(1, 0) * m(2, 1) - m(1, 1) * m(2, 0)) / det,
                (m(0, 1) * m(2, 0) - m(0, 0) * m(2, 1)) / det,
                (m(0, 0) * m(1, 1) - m(0, 1) * m(1, 0)) / det,
            ],
        ];
        let t = [a.rows[0][3], a.rows[1][3], a.rows[2][3]];
        let mut rows = [[0.0; 4]; 3];
        for r in 0..3 {
            rows[r][..3].copy_from_slice(&inv[r]);
            rows[r][3] = -(inv[r][0] * t[0] + inv[r][1] * t[1] + inv[r][2] * t[2]);
        }
        let inv = Affine3 { rows };
        inv.is_finite().then_some(inv)
    }
}

/// A 2D affine map `(i, j) ↦ (x, y)`, rows `[a, b, t]`.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Affine2 {
    /// Rows of `[M | t]`.
    pub rows: [[f64; 3]; 2],
}

impl Affine2 {
    /// The identity map.
    pub const IDENTITY: Affine2 = Affine2 {
        rows: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
    };
    /// Applies the map.
    pub fn apply(&self, p: [f64; 2]) -> [f64; 2] {
        self.rows.map(|r| r[0] * p[0] + r[1] * p[1] + r[2])
    }
}

/// The lateral grid shared by a survey's seismic cubes and horizons: inline and crossline
/// numbering and where each grid node lies in the world.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurveyGrid {
    /// First inline number.
    pub inline0: f64,
    /// Inline increment between grid rows.
    pub inline_step: f64,
    /// Number of inlines.
    pub n_inline: u64,
    /// First crossline number.
    pub xline0: f64,
    /// Crossline increment between grid columns.
    pub xline_step: f64,
    /// Number of crosslines.
    pub n_xline: u64,
    /// Grid index `(i, j)` (i along inlines, j along crosslines) to world `(x, y)`.
    pub to_world: Affine2,
}

impl SurveyGrid {
    /// Grid index of an (inline, crossline) pair, if it falls on a node inside the grid.
    pub fn index_of(&self, inline: f64, xline: f64) -> Option<(u64, u64)> {
        let fi = (inline - self.inline0) / self.inline_step;
        let fj = (xline - self.xline0) / self.xline_step;
        let (i, j) = (fi.round(), fj.round());
        let on_node = (fi - i).abs() < 1e-6 && (fj - j).abs() < 1e-6;
        (on_node && i >= 0.0 && j >= 0.0 && (i as u64) < self.n_inline && (j as u64) < self.n_xline)
            .then_some((i as u64, j as u64))
    }
}

/// Result of fitting an affine map from grid indices to world coordinates.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct AffineFit {
    /// The fitted map.
    pub map: Affine2,
    /// Root-mean-square distance between the fitted and the given points.
    pub rms_residual: f64,
    /// Largest distance between a fitted and a given point.
    pub max_residual: f64,
}

/// Least-squares fit of `(i, j) ↦ (x, y)` from point pairs.
///
/// Coordinates are centred before forming the normal equations, so UTM-sized values lose no
/// precision. Returns `None` when the points do not span two independent directions.
pub fn fit_affine2(points: &[([f64; 2], [f64; 2])]) -> Option<AffineFit> {
    let n = points.len() as f64;
    if points.len() < 3 {
        return None;
    }
    let mut mi = [0.0; 2];
    let mut mw = [0.0; 2];
    for (g, w) in points {
        mi[0] += g[0];
        mi[1] += g[1];
        mw[0] += w[0];
        mw[1] += w[1];
    }
    mi = mi.map(|v| v / n);
    mw = mw.map(|v| v / n);
    // Normal equations for centred data: [Sii Sij; Sij Sjj] · [a b]ᵀ = [Sxi Sxj]ᵀ.
    let (mut sii, mut sij, mut sjj) = (0.0, 0.0, 0.0);
    let mut rhs = [[0.0; 2]; 2];
    for (g, w) in points {
        let (di, dj) = (g[0] - mi[0], g[1] - mi[1]);
        sii += di * di;
        sij += di * dj;
        sjj += dj * dj;
        for k in 0..2 {
            let dw = w[k] - mw[k];
            rhs[k][0] += dw * di;
            rhs[k][1] += dw * dj;
        }
    }
    let det = sii * sjj - sij * sij;
    if !(det.abs() > 1e-12 * (sii * sjj).max(1e-300)) {
        return None;
    }
    let mut rows = [[0.0; 3]; 2];
    for k in 0..2 {
        let a = (rhs[k][0] * sjj - rhs[k][1] * sij) / det;
        let b = (rhs[k][1] * sii - rhs[k][0] * sij) / det;
        rows[k] = [a, b, mw[k] - a * mi[0] - b * mi[1]];
    }
    let map = Affine2 { rows };
    let (mut s2, mut mx) = (0.0f64, 0.0f64);
    for (g, w) in points {
        // Residual computed relative to the centroid to avoid cancellation at UTM magnitudes.
        let p = [
            rows[0][0] * (g[0] - mi[0]) + rows[0][1] * (g[1] - mi[1]) - (w[0] - mw[0]),
            rows[1][0] * (g[0] - mi[0]) + rows[1][1] * (g[1] - mi[1]) - (w[1] - mw[1]),
        ];
        let d = (p[0] * p[0] + p[1] * p[1]).sqrt();
        s2 += d * d;
        mx = mx.max(d);
    }
    Some(AffineFit {
        map,
        rms_residual: (s2 / n).sqrt(),
        max_residual: mx,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Singularity is judged by shape, not scale: unit columns whose determinant is 1e-15
    /// are singular, columns of 1e-5 (det 1e-15) are not.
    #[test]
    fn inverse_judges_singularity_relative_to_the_columns() {
        let sheared = Affine3 {
            rows: [
                [1.0, 1.0, 0.0, 0.0],
                [0.0, 1e-15, 0.0, 0.0],
                [0.0, 0.0, 1.0, 0.0],
            ],
        };
        assert!(sheared.inverse().is_none());
        let small = Affine3::scale_offset([1e-5; 3], [6e6, 5e5, 0.0]);
        let inv = small.inverse().expect("a small scale is invertible");
        let p = inv.apply(small.apply([1.0, 2.0, 3.0]));
        assert!(
            (p[0] - 1.0).abs() < 1e-6 && (p[2] - 3.0).abs() < 1e-6,
            "{p:?}"
        );
    }

    #[test]
    fn inverse_round_trips() {
        let a = Affine3 {
            rows: [
                [2.0, 0.3, 0.0, 605000.0],
                [-0.3, 2.0, 0.0, 6075000.0],
                [0.0, 0.0, 4.0, 12.0],
            ],
        };
        let i = a.inverse().unwrap();
        let p = [3.0, 7.0, 11.0];
        let q = i.apply(a.apply(p));
        for k in 0..3 {
            assert!((q[k] - p[k]).abs() < 1e-6, "{q:?}");
        }
        let flat = Affine3::scale_offset([1.0, 1.0, 0.0], [0.0; 3]);
        assert!(flat.inverse().is_none());
    }

    #[test]
    fn fit_recovers_rotated_utm_grid_exactly() {
        let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
        let truth = Affine2 {
            rows: [
                [25.0 * c, -12.5 * s, 612_345.6],
                [25.0 * s, 12.5 * c, 6_078_901.2],
            ],
        };
        let pts: Vec<_> = (0..50)
            .flat_map(|i| (0..40).map(move |j| [i as f64, j as f64]))
            .map(|g| (g, truth.apply(g)))
            .collect();
        let fit = fit_affine2(&pts).unwrap();
        assert!(fit.max_residual < 1e-6, "{fit:?}");
        for r in 0..2 {
            for k in 0..3 {
                assert!((fit.map.rows[r][k] - truth.rows[r][k]).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn fit_rejects_collinear_points() {
        let pts: Vec<_> = (0..10)
            .map(|i| ([i as f64, 0.0], [i as f64, 1.0]))
            .collect();
        assert!(fit_affine2(&pts).is_none());
    }

    #[test]
    fn survey_index_of() {
        let g = SurveyGrid {
            inline0: 110.0,
            inline_step: 2.0,
            n_inline: 225,
            xline0: 550.0,
            xline_step: 2.0,
            n_xline: 300,
            to_world: Affine2::IDENTITY,
        };
        assert_eq!(g.index_of(110.0, 550.0), Some((0, 0)));
        assert_eq!(g.index_of(558.0, 1148.0), Some((224, 299)));
        assert_eq!(g.index_of(111.0, 550.0), None);
        assert_eq!(g.index_of(560.0, 550.0), None);
    }
}
