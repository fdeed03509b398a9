//! Levels of detail: level transitions across region boundaries, an atlas smaller than the
//! working set, τ very small and very large.

use crate::harness::*;
use crate::Case;
use strata_common::geo::Affine3;
use strata_common::scene::Scene;

pub fn cases() -> Vec<Case> {
    vec![
        Case {
            no: 32,
            name: "level-transitions-across-regions",
            reference: "the whole scene as one region (in process)",
            tol: 1e-5,
            why: "a sample's level depends on its distance, not on its region, so regions change \
                  nothing but float reassociation",
            long_rays: false,
            run: transitions,
        },
        Case {
            no: 33,
            name: "atlas-smaller-than-working-set",
            reference: "the same view with an atlas that holds everything, against the same view at \
                        the coarsest level",
            tol: 1.0,
            why: "a full atlas falls back to coarser resident levels: the image may be no further \
                  from the full-atlas one than the coarsest level's (error measured as that ratio), \
                  and the render must report that it did not converge",
            long_rays: false,
            run: small_atlas,
        },
        Case {
            no: 34,
            name: "tau-tiny-and-huge",
            reference: "analytic slab 1-(1-a)^32 at τ = 1e-6 (finest level) and τ = 1e6 (coarsest)",
            tol: 2e-5,
            why: "every level of a constant volume holds the constant, and a level's box is the data's \
                  box, so the slab is the same at any level; 32 blend steps in f32",
            long_rays: false,
            run: tau_extremes,
        },
    ]
}

/// A 96³ smooth volume in 32-sample pages (levels 0..2) seen from close by, so that near
/// samples use level 0 and far ones coarser levels.
fn lod_scene(ctx: &Ctx) -> Scene {
    let store = volume(ctx, "v", [96, 96, 96], Affine3::IDENTITY, 32, smooth);
    let mut r = settings(64, 48);
    r.tau = 1.0;
    r.adaptive_step = true;
    scene(
        vec![seismic(store, [-1.0, 1.0])],
        vec![],
        camera(
            [-10.0, -20.0, 60.0],
            [48.0, 48.0, 40.0],
            [0.0, 0.0, 1.0],
            35.0,
        ),
        r,
    )
}

/// The levels of dataset 0 that a converged CPU frame of the scene samples.
fn levels_sampled(s: &Scene) -> Res<std::collections::BTreeSet<u8>> {
    use strata_worker::engine::Engine;
    let mut s = s.clone();
    s.render.backend = strata_common::scene::Backend::Cpu;
    let mut e = Engine::new(&s).map_err(|e| format!("{e:#}"))?;
    let view = e
        .view(s.render.width, s.render.height)
        .map_err(|e| format!("{e:#}"))?;
    let region = e.scene_region();
    e.render_batch(&view, &region)
        .map_err(|e| format!("{e:#}"))?;
    let f = e
        .render_frame(&view, &region)
        .map_err(|e| format!("{e:#}"))?;
    Ok(f.feedback
        .coverage
        .keys()
        .map(|&k| strata_common::ids::PageId(k).level())
        .collect())
}

fn transitions(ctx: &Ctx) -> Res<f64> {
    let s = lod_scene(ctx);
    // The case's premise: the view samples more than one level.
    let levels = levels_sampled(&s)?;
    if levels.len() < 2 {
        return Err(format!(
            "the view samples levels {levels:?} only: mis-built"
        ));
    }
    let tree = decomposition(&s, WORKERS)?;
    let whole = ctx.whole_reference(&s)?;
    let split = ctx.render_regions(&s, &tree)?;
    shows(&whole, 0.3, "the volume")?;
    diff(&whole, &split)
}

fn small_atlas(ctx: &Ctx) -> Res<f64> {
    let mut s = lod_scene(ctx);
    let full = ctx.render(&s)?;
    let mut coarsest = s.clone();
    coarsest.render.tau = 1e6;
    let coarsest = ctx.render(&coarsest)?;
    s.render.atlas_mb = 1;
    let (small, converged) = ctx.render_any(&s)?;
    if converged {
        return Err("a 1 MiB atlas held the whole working set: mis-built".into());
    }
    // The fallback to coarser levels may cost at most what the coarsest level costs.
    Ok(diff(&full, &small)? / diff(&full, &coarsest)?.max(1e-6))
}

fn tau_extremes(ctx: &Ctx) -> Res<f64> {
    let a = 0.05;
    let store = volume(ctx, "c", [32, 32, 32], Affine3::IDENTITY, 32, |_, _, _| 1.0);
    let mut err = 0.0f64;
    for tau in [1e-6, 1e6] {
        let mut r = settings(9, 9);
        r.tau = tau;
        let s = scene(
            vec![grey(store.clone(), [0.0, 2.0], a)],
            vec![],
            head_on_camera(),
            r,
        );
        // The premise: τ picks the level (the constant volume is the same at every level,
        // so the slab alone could not tell that τ was heeded).
        let levels = levels_sampled(&s)?;
        let want_finest = tau < 1.0;
        if levels.is_empty() || want_finest != (levels.iter().all(|&l| l == 0)) {
            return Err(format!("τ = {tau:e} sampled levels {levels:?}"));
        }
        let img = ctx.render(&s)?;
        err = err.max(slab_error(
            &s,
            &img,
            a,
            [-0.5, 31.5],
            [31.5, 31.5],
            0.5,
            40,
        )?);
    }
    Ok(err)
}
