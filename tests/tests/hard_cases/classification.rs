//! Classification: pre-integrated transfer functions (`render.preintegrated`) against the
//! analytic integral of a transfer function too thin for point samples.

use crate::harness::*;
use crate::Case;
use strata_common::geo::Affine3;

pub fn cases() -> Vec<Case> {
    vec![Case {
        no: 35,
        name: "preintegrated-thin-peak",
        reference: "the absorption–emission integral along a linear ramp through an opacity \
                    peak 0.04 of the window wide, in f64 by quadrature, at steps 0.5, 2 and 8 \
                    voxels (at 8 every point sample misses the peak), at 8 also split into the \
                    workers' regions",
        tol: 3e-3,
        why: "a linear value is integrated exactly up to the tables: the transfer function's \
              1024 entries and the pre-integrated 256² ones, interpolated bilinearly, round the \
              peak's apex off (2.2e-3 at step 0.5, whose segments span 2 table entries; less at \
              coarser steps)",
        long_rays: false,
        run: thin_peak,
    }]
}

/// Opacity per voxel of the peak: a tent of height `PEAK` on `[0.48, 0.52]`.
const PEAK: f64 = 0.5;
const LO: f64 = 0.48;
const HI: f64 = 0.52;

fn tent(v: f64) -> f64 {
    let mid = 0.5 * (LO + HI);
    if v <= LO || v >= HI {
        0.0
    } else if v < mid {
        PEAK * (v - LO) / (mid - LO)
    } else {
        PEAK * (HI - v) / (HI - mid)
    }
}

/// The premultiplied RGBA of the ray down the column: value `z / 63` at depth z, grey
/// colour equal to the value, extinction `−ln(1 − tent(v))` per voxel.
fn analytic() -> [f64; 4] {
    // The peak lies in z ∈ [63·0.48, 63·0.52]; outside it nothing absorbs or emits.
    let (z0, z1) = (63.0 * LO - 0.5, 63.0 * HI + 0.5);
    let n = 400_000;
    let dz = (z1 - z0) / n as f64;
    let (mut c, mut t) = (0.0f64, 1.0f64);
    for i in 0..n {
        let z = z0 + (i as f64 + 0.5) * dz;
        let v = z / 63.0;
        let sigma = -(-tent(v)).ln_1p();
        let a = -(-sigma * dz).exp_m1();
        c += t * a * v;
        t *= 1.0 - a;
    }
    [c, c, c, 1.0 - t]
}

fn thin_peak(ctx: &Ctx) -> Res<f64> {
    let store = volume(
        ctx,
        "ramp64",
        [4, 4, 64],
        Affine3::IDENTITY,
        32,
        |_, _, k| k as f32 / 63.0,
    );
    let layer = strata_tests::scenes::volume_layer(
        store,
        "grey",
        [0.0, 1.0],
        vec![
            [0.0, 0.0],
            [LO, 0.0],
            [0.5 * (LO + HI), PEAK],
            [HI, 0.0],
            [1.0, 0.0],
        ],
    );
    let want = analytic();
    if !(want[3] > 0.3 && want[3] < 0.7) {
        return Err(format!("the peak's opacity is {}: mis-built", want[3]));
    }
    let mut err = 0.0f64;
    for step in [0.5, 2.0, 8.0] {
        // Down the column's centre (x = y = 1.5), so the value is linear along the ray.
        let mut s = scene(
            vec![layer.clone()],
            vec![],
            camera([1.5, 1.5, -100.0], [1.5, 1.5, 0.0], [0.0, 1.0, 0.0], 0.1),
            settings(3, 3),
        );
        s.render.step = step;
        s.render.preintegrated = true;
        let got = at(&ctx.render(&s)?, 3, 1, 1);
        err = err.max(err4(got, want));
        if step == 8.0 {
            // Split into the workers' regions: where the peak's segment crosses a split
            // plane next to a hidden brick, each region still integrates its share of it.
            let tree = decomposition(&s, WORKERS)?;
            let split = at(&ctx.render_regions(&s, &tree)?, 3, 1, 1);
            err = err.max(err4(split, want));
            // The construction: samples at z ≡ 4 (mod 8) see values 0.444 and 0.571 on
            // either side of the peak, so point samples show nothing.
            s.render.preintegrated = false;
            let post = at(&ctx.render(&s)?, 3, 1, 1);
            if post[3] > 1e-6 {
                return Err(format!(
                    "point samples at step 8 see the peak ({post:?}): mis-built"
                ));
            }
        }
    }
    Ok(err)
}
