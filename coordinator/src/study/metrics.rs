//! Image differences for the accuracy study: RMSE and largest error in premultiplied
//! linear RGBA (what the renderer computes), and 1 − SSIM of the displayed image (what a
//! viewer sees).
//!
//! SSIM is the standard one (Wang et al. 2004): an 11-tap Gaussian window of σ = 1.5 on the
//! luma of the sRGB-encoded image, flattened over the scene's background, with
//! `C1 = (0.01)²`, `C2 = (0.03)²` for values in [0, 1]. It is written here rather than taken
//! from `dssim-core` because that crate is AGPL-licensed.

use strata_common::image::Rgba;

/// Differences of one image from the reference.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct Errors {
    /// Root mean square over all pixels and the four channels.
    pub rmse: f64,
    /// Largest absolute difference of any channel.
    pub max: f64,
    /// 1 − mean SSIM of the displayed images (0: identical).
    pub dssim: f64,
}

/// Compares `img` with `reference` (both `w`×`h`, premultiplied linear RGBA, row 0 on top).
pub fn compare(img: &[Rgba], reference: &[Rgba], w: usize, h: usize, bg: [f32; 3]) -> Errors {
    assert_eq!(img.len(), w * h);
    assert_eq!(reference.len(), w * h);
    let (rmse, max) = rmse_max(img, reference);
    let dssim = 1.0 - ssim(&luma(img, bg), &luma(reference, bg), w, h);
    Errors { rmse, max, dssim }
}

/// RMSE and largest absolute difference over every channel; a non-finite value counts as
/// an error of 1 (the renderer must never produce one).
pub fn rmse_max(a: &[Rgba], b: &[Rgba]) -> (f64, f64) {
    let mut s = 0.0f64;
    let mut m = 0.0f64;
    for (p, q) in a.iter().zip(b) {
        for c in 0..4 {
            let d = (p[c] as f64 - q[c] as f64).abs();
            let d = if d.is_finite() { d } else { 1.0 };
            s += d * d;
            m = m.max(d);
        }
    }
    ((s / (a.len().max(1) * 4) as f64).sqrt(), m)
}

fn srgb(x: f64) -> f64 {
    let x = if x.is_finite() {
        x.clamp(0.0, 1.0)
    } else {
        0.0
    };
    if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }
}

/// Rec. 709 luma of the sRGB-encoded image flattened over `bg`, as a viewer sees it.
pub fn luma(img: &[Rgba], bg: [f32; 3]) -> Vec<f64> {
    img.iter()
        .map(|p| {
            let a = (p[3] as f64).clamp(0.0, 1.0);
            let c = [0, 1, 2].map(|k| srgb(p[k] as f64 + (1.0 - a) * bg[k] as f64));
            0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
        })
        .collect()
}

/// The 11-tap Gaussian of σ = 1.5, normalised.
fn gaussian() -> [f64; 11] {
    let mut g = [0.0; 11];
    for (i, v) in g.iter_mut().enumerate() {
        let x = i as f64 - 5.0;
        *v = (-x * x / (2.0 * 1.5 * 1.5)).exp();
    }
    let s: f64 = g.iter().sum();
    g.map(|v| v / s)
}

/// Separable Gaussian blur with the window clipped (and renormalised) at the edges.
fn blur(x: &[f64], w: usize, h: usize) -> Vec<f64> {
    let g = gaussian();
    let pass = |src: &[f64], along_x: bool| {
        let mut out = vec![0.0; src.len()];
        for y in 0..h {
            for i in 0..w {
                let (mut s, mut ws) = (0.0, 0.0);
                for (k, gk) in g.iter().enumerate() {
                    let (xx, yy) = if along_x {
                        (i as i64 + k as i64 - 5, y as i64)
                    } else {
                        (i as i64, y as i64 + k as i64 - 5)
                    };
                    if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                        s += gk * src[yy as usize * w + xx as usize];
                        ws += gk;
                    }
                }
                out[y * w + i] = s / ws;
            }
        }
        out
    };
    pass(&pass(x, true), false)
}

/// Mean SSIM of two grey images with values in [0, 1].
pub fn ssim(a: &[f64], b: &[f64], w: usize, h: usize) -> f64 {
    const C1: f64 = 0.01 * 0.01;
    const C2: f64 = 0.03 * 0.03;
    let prod = |f: &dyn Fn(f64, f64) -> f64| -> Vec<f64> {
        a.iter().zip(b).map(|(&x, &y)| f(x, y)).collect::<Vec<_>>()
    };
    let mu_a = blur(a, w, h);
    let mu_b = blur(b, w, h);
    let aa = blur(&prod(&|x, _| x * x), w, h);
    let bb = blur(&prod(&|_, y| y * y), w, h);
    let ab = blur(&prod(&|x, y| x * y), w, h);
    let mut sum = 0.0;
    for i in 0..a.len() {
        let (ma, mb) = (mu_a[i], mu_b[i]);
        let va = (aa[i] - ma * ma).max(0.0);
        let vb = (bb[i] - mb * mb).max(0.0);
        let cov = ab[i] - ma * mb;
        sum +=
            ((2.0 * ma * mb + C1) * (2.0 * cov + C2)) / ((ma * ma + mb * mb + C1) * (va + vb + C2));
    }
    sum / a.len().max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(w: usize, h: usize) -> Vec<Rgba> {
        (0..w * h)
            .map(|i| {
                let v = (i % w) as f32 / w as f32 * 0.8;
                [v * 0.5, v * 0.4, v * 0.3, v]
            })
            .collect()
    }

    #[test]
    fn identical_images_have_no_error() {
        let a = ramp(24, 16);
        let e = compare(&a, &a, 24, 16, [0.0; 3]);
        assert_eq!(e.rmse, 0.0);
        assert_eq!(e.max, 0.0);
        assert!(e.dssim.abs() < 1e-12, "{e:?}");
    }

    #[test]
    fn rmse_and_max_of_a_uniform_offset() {
        let a = ramp(10, 10);
        let b: Vec<Rgba> = a.iter().map(|p| [p[0] + 0.01, p[1], p[2], p[3]]).collect();
        let (r, m) = rmse_max(&b, &a);
        // One channel of four is off by 0.01 everywhere: RMSE = 0.01 / 2.
        assert!((r - 0.005).abs() < 1e-7, "{r}");
        assert!((m - 0.01).abs() < 1e-7, "{m}");
    }

    #[test]
    fn non_finite_pixels_count_as_full_errors() {
        let a = vec![[0.0f32; 4]; 4];
        let mut b = a.clone();
        b[2][1] = f32::NAN;
        assert_eq!(rmse_max(&b, &a).1, 1.0);
    }

    #[test]
    fn ssim_of_constant_images_follows_the_luminance_term() {
        // Flat images: variances and covariance vanish, so SSIM is the luminance term
        // (2 μa μb + C1) / (μa² + μb² + C1) exactly.
        let (w, h) = (16, 12);
        let a = vec![0.5; w * h];
        let b = vec![0.6; w * h];
        let expect = (2.0 * 0.5 * 0.6 + 1e-4) / (0.25 + 0.36 + 1e-4);
        assert!((ssim(&a, &b, w, h) - expect).abs() < 1e-12);
    }

    #[test]
    fn ssim_sees_structure_that_rmse_weighs_the_same() {
        // Noise and a uniform shift with the same RMSE: SSIM penalises the noise far more.
        let (w, h) = (32, 32);
        let base: Vec<f64> = (0..w * h)
            .map(|i| 0.3 + 0.4 * (i % w) as f64 / w as f64)
            .collect();
        let shifted: Vec<f64> = base.iter().map(|v| v + 0.05).collect();
        let noisy: Vec<f64> = base
            .iter()
            .enumerate()
            .map(|(i, v)| v + if (i * 7919) % 2 == 0 { 0.05 } else { -0.05 })
            .collect();
        let s_shift = ssim(&base, &shifted, w, h);
        let s_noise = ssim(&base, &noisy, w, h);
        assert!(s_noise < s_shift - 0.05, "noise {s_noise}, shift {s_shift}");
        assert!(s_shift < 1.0);
    }
}
