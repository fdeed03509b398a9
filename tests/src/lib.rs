//! Shared helpers for Strata's end-to-end tests.

use std::path::PathBuf;
use strata_common::pyramid::Dim;
use strata_common::store::{DataKind, PageStore};

/// The shared real-data folder (`../shared/data/real` beside the checkout).
pub fn real_data(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/real")
        .join(rel)
}

pub use strata_coordinator::inspect::level_grid;

/// Bitwise equality that treats all NaNs as equal.
pub fn same(a: f32, b: f32) -> bool {
    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
}

/// Checks that every page of every level holds, border included, exactly the level's
/// samples at its position (edge replicas for volumes, holes outside a horizon's grid).
/// Returns the first mismatch as a message.
pub fn check_borders(store: &PageStore) -> Result<(), String> {
    let pyr = store.pyramid();
    let horizon = store.header().kind == DataKind::Horizon;
    let pd = pyr.page_dims().map(|v| v as i64);
    for l in 0..pyr.level_count() {
        let grid = level_grid(store, l).map_err(|e| e.to_string())?;
        let dims = pyr.level(l).dims.map(|d| d as i64);
        for br in pyr.bricks_in_z_order(l) {
            let page = store.read_page(pyr.id(l, br)).map_err(|e| e.to_string())?;
            let o = pyr.page_origin(br);
            for pz in 0..pd[2] {
                for py in 0..pd[1] {
                    for px in 0..pd[0] {
                        let g = [o[0] + px, o[1] + py, o[2] + pz];
                        let outside = (0..3).any(|a| g[a] < 0 || g[a] >= dims[a]);
                        let want = if horizon && outside {
                            f32::NAN
                        } else {
                            let c = [0, 1, 2].map(|a| g[a].clamp(0, dims[a] - 1));
                            grid[((c[2] * dims[1] + c[1]) * dims[0] + c[0]) as usize]
                        };
                        let got = page.samples[((pz * pd[1] + py) * pd[0] + px) as usize];
                        if !same(got, want) {
                            return Err(format!("level {l} brick {br:?} local ({px},{py},{pz}) global {g:?}: page has {got}, level has {want}"));
                        }
                    }
                }
            }
        }
        let _ = pyr.dim() == Dim::Two;
    }
    Ok(())
}

/// Checks that every coarse level equals the store's filter applied to the level below
/// (2×2(×2) children, indices clamped at the level's end), quantized to the sample type.
pub fn check_coarse_levels(store: &PageStore) -> Result<(), String> {
    let h = store.header();
    let pyr = store.pyramid();
    let flat = pyr.dim() == Dim::Two;
    for l in 1..pyr.level_count() {
        let fine = level_grid(store, l - 1).map_err(|e| e.to_string())?;
        let coarse = level_grid(store, l).map_err(|e| e.to_string())?;
        let fd = pyr.level(l - 1).dims;
        let cd = pyr.level(l).dims;
        for z in 0..cd[2] {
            for y in 0..cd[1] {
                for x in 0..cd[0] {
                    let mut kids = Vec::with_capacity(8);
                    for dz in if flat { 0..1 } else { 0..2 } {
                        for dy in 0..2 {
                            for dx in 0..2 {
                                let f = [
                                    (2 * x + dx).min(fd[0] - 1),
                                    (2 * y + dy).min(fd[1] - 1),
                                    if flat { 0 } else { (2 * z + dz).min(fd[2] - 1) },
                                ];
                                kids.push(fine[((f[2] * fd[1] + f[1]) * fd[0] + f[0]) as usize]);
                            }
                        }
                    }
                    let want = h.sample_type.quantize(h.filter.apply(&kids));
                    let got = coarse[((z * cd[1] + y) * cd[0] + x) as usize];
                    if !same(got, want) {
                        return Err(format!("level {l} sample ({x},{y},{z}): stored {got}, filter of level {} gives {want}", l - 1));
                    }
                }
            }
        }
    }
    Ok(())
}
