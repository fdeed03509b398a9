//! The worker's data sets: open stores with their transforms, and the per-page value
//! bounds (from the store index, so known without loading a page) that drive empty-space
//! skipping for volumes and the min-max quadtree for horizons.

use anyhow::{bail, Context, Result};
use std::sync::Arc;
use strata_common::geo::Affine3;
use strata_common::kd::Region;
use strata_common::pyramid::Pyramid;
use strata_common::scene::{HorizonLayer, Scene, VolumeLayer};
use strata_common::store::{DataKind, PageStore};
use strata_common::tf::{ColorMap, TransferFunction};

/// A volume to draw.
pub struct Volume {
    /// Data-set number (page keys carry it).
    pub ds: u16,
    /// The store.
    pub store: Arc<PageStore>,
    /// Its page tree.
    pub pyramid: Pyramid,
    /// Index → world.
    pub to_world: Affine3,
    /// Transfer function.
    pub tf: TransferFunction,
    /// `[min, max]` per page, in page-table order (NaN range for empty pages).
    pub bounds: Vec<[f32; 2]>,
    /// Each page's feedback key (data set, level, Morton index), in page-table order: the
    /// march records one per brick it enters, so the key is looked up, not encoded.
    pub page_keys: Vec<u64>,
    /// Slices drawn through it.
    pub slices: Vec<Slice>,
}

/// A slice of a volume, checked against its grid.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct Slice {
    /// Grid axis it is normal to.
    pub axis: usize,
    /// Level-0 index along that axis.
    pub index: f32,
    /// Opacity.
    pub opacity: f32,
}

/// A horizon to draw.
pub struct Horizon {
    /// Data-set number.
    pub ds: u16,
    /// The store.
    pub store: Arc<PageStore>,
    /// Its tile tree.
    pub pyramid: Pyramid,
    /// Index (i, j, height) → world.
    pub to_world: Affine3,
    /// Straight RGB for `color_by = "constant"`.
    pub color: [f32; 3],
    /// Colour map over the height range for `color_by = "depth"`.
    pub depth_map: Option<(ColorMap, [f32; 2])>,
    /// `color_by = "volume"`: the volume whose value colours the surface (then `color` is
    /// the no-data colour).
    pub attribute: Option<usize>,
    /// Opacity.
    pub opacity: f32,
    /// `[min, max]` height per tile, in page-table order.
    pub bounds: Vec<[f32; 2]>,
    /// The tile tree's padded boxes, in page-table order.
    pub boxes: Vec<crate::horizon::TileBox>,
}

/// Every page `(level, brick)` of a pyramid in page-table order (`PageTable::index`: level
/// by level, x fastest).
fn pages_in_table_order(p: &Pyramid) -> impl Iterator<Item = (usize, [u32; 3])> + '_ {
    p.levels().iter().enumerate().flat_map(|(l, lev)| {
        let [nx, ny, nz] = lev.bricks;
        (0..nz).flat_map(move |z| (0..ny).flat_map(move |y| (0..nx).map(move |x| (l, [x, y, z]))))
    })
}

/// Each page's `[min, max]` from the index, `NaN` where nothing lies under it. A page with
/// no valid sample of its own keeps the bounds ingest widened to its children's: a horizon's
/// coarse tile is a hole wherever one of its 2×2 children is (`HorizonMean`), so a surface
/// picked on every other line has all-hole coarse tiles over real heights, and a search
/// that stopped at them found nothing at any distance.
fn page_bounds(store: &PageStore) -> Vec<[f32; 2]> {
    let p = store.pyramid();
    pages_in_table_order(p)
        .map(|(l, b)| match store.entry(p.id(l, b)) {
            Some(e) if e.min <= e.max => [e.min, e.max],
            _ => [f32::NAN, f32::NAN],
        })
        .collect()
}

/// Every page's key in page-table order.
fn page_keys(ds: u16, p: &Pyramid) -> Vec<u64> {
    pages_in_table_order(p)
        .map(|(l, b)| crate::atlas::page_key(ds, p, l, b))
        .collect()
}

fn open(path: &std::path::Path, kind: DataKind) -> Result<Arc<PageStore>> {
    let s = PageStore::open(path).with_context(|| format!("opening {}", path.display()))?;
    if s.header().kind != kind {
        bail!(
            "{}: expected a {:?} store, found a {:?} store",
            path.display(),
            kind,
            s.header().kind
        );
    }
    if !s.header().transform.is_finite() {
        bail!(
            "{}: the index→world transform is not finite",
            path.display()
        );
    }
    // The casters map world rays back into the grid.
    if s.header().transform.inverse().is_none() {
        bail!(
            "{}: the index→world transform {:?} is singular (expected one that maps the grid onto a volume)",
            path.display(),
            s.header().transform.rows
        );
    }
    Ok(Arc::new(s))
}

/// Percentile of |amplitude| at which a seismic volume's default window clips (the usual
/// default of seismic interpretation tools).
pub const SEISMIC_CLIP_PERCENTILE: f64 = 99.5;

/// The value window of a layer that sets none. For a diverging map (`seismic`, `bwr`, or one
/// of them reversed) over signed
/// data: ±the [`SEISMIC_CLIP_PERCENTILE`]th percentile of |amplitude|, so white sits exactly
/// at zero and rare spikes do not wash the section out; the percentile is the one ingest
/// computed over every level-0 sample (`StoreHeader::stats`), or, for a store without
/// statistics (format 1), taken over the root page's valid samples (the whole volume,
/// coarsened, one page read). Otherwise the
/// store's value range. A constant store (range `[v, v]`) gets a window centred on `v`, so
/// its value maps to the middle of the colour map instead of the layer being refused.
fn default_window(store: &PageStore, layer: &VolumeLayer) -> Result<[f64; 2]> {
    let [lo, hi] = data_window(store, layer)?;
    if lo == hi && lo.is_finite() {
        let half = 0.5 * lo.abs().max(1.0);
        return Ok([lo - half, lo + half]);
    }
    Ok([lo, hi])
}

fn data_window(store: &PageStore, layer: &VolumeLayer) -> Result<[f64; 2]> {
    let range = store.header().value_range;
    if !strata_common::tf::is_diverging(&layer.colormap) || !(range[0] < 0.0) {
        return Ok(range);
    }
    // Computed at ingest over every level-0 sample.
    if let Some(c) = store
        .header()
        .stats
        .as_ref()
        .and_then(|s| s.abs_percentile(SEISMIC_CLIP_PERCENTILE))
        .filter(|&c| c > 0.0)
    {
        return Ok([-c, c]);
    }
    let p = store.pyramid();
    let top = p.level_count() - 1;
    let root = store
        .read_page(p.id(top, [0, 0, 0]))
        .with_context(|| format!("volume {}: reading the root page", layer.store.display()))?;
    let mut mag: Vec<f32> = root
        .samples
        .iter()
        .filter(|v| v.is_finite())
        .map(|v| v.abs())
        .collect();
    if mag.is_empty() {
        return Ok(range);
    }
    let k = ((mag.len() - 1) as f64 * SEISMIC_CLIP_PERCENTILE / 100.0).round() as usize;
    let (_, c, _) = mag.select_nth_unstable_by(k, f32::total_cmp);
    let c = *c as f64;
    Ok(if c > 0.0 { [-c, c] } else { range })
}

impl Volume {
    /// Opens a volume layer as data set `ds`.
    pub fn open(layer: &VolumeLayer, ds: u16) -> Result<Self> {
        let store = open(&layer.store, DataKind::Volume)?;
        let h = store.header();
        let window = match layer.window {
            Some(w) => w,
            None => default_window(&store, layer)?,
        };
        let tf = TransferFunction::from_layer(layer, window)
            .with_context(|| format!("volume {}", layer.store.display()))?;
        let dims = store.pyramid().level(0).dims;
        if layer.slices.len() > strata_common::gpu::MAX_SLICES {
            bail!(
                "volume {}: {} slices; at most {} per volume are drawn",
                layer.store.display(),
                layer.slices.len(),
                strata_common::gpu::MAX_SLICES
            );
        }
        let slices = layer
            .slices
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let a = s.axis.index();
                let last = dims[a].saturating_sub(1) as f64;
                if !(s.index >= 0.0 && s.index <= last) {
                    bail!(
                        "volume {}: slice {i} ({:?}) at index {} lies outside the grid's 0..={last}",
                        layer.store.display(),
                        s.axis,
                        s.index
                    );
                }
                if !(0.0..=1.0).contains(&s.opacity) {
                    bail!(
                        "volume {}: slice {i} opacity must lie in [0, 1], got {}",
                        layer.store.display(),
                        s.opacity
                    );
                }
                Ok(Slice {
                    axis: a,
                    index: s.index as f32,
                    opacity: s.opacity as f32,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Volume {
            slices,
            ds,
            pyramid: store.pyramid().clone(),
            to_world: h.transform,
            tf,
            bounds: page_bounds(&store),
            page_keys: page_keys(ds, store.pyramid()),
            store,
        })
    }

    /// Level-0 dims.
    pub fn dims(&self) -> [u64; 3] {
        self.pyramid.level(0).dims
    }
}

impl Horizon {
    /// Opens a horizon layer as data set `ds`.
    pub fn open(layer: &HorizonLayer, ds: u16, volumes: usize) -> Result<Self> {
        let store = open(&layer.store, DataKind::Horizon)?;
        let h = store.header();
        if !(0.0..=1.0).contains(&layer.opacity) {
            bail!(
                "horizon {}: opacity must lie in [0, 1], got {}",
                layer.store.display(),
                layer.opacity
            );
        }
        let mut attribute = None;
        let depth_map = match layer.color_by.as_str() {
            "constant" => None,
            "volume" => {
                if layer.volume >= volumes {
                    bail!(
                        "horizon {}: color_by = \"volume\" names volume {}, but the scene has {volumes} volume(s) (0-based)",
                        layer.store.display(),
                        layer.volume
                    );
                }
                attribute = Some(layer.volume);
                None
            }
            "depth" => Some((
                ColorMap::named(&layer.colormap)?,
                [h.value_range[0] as f32, h.value_range[1] as f32],
            )),
            other => bail!(
                "horizon {}: color_by must be \"constant\", \"depth\" or \"volume\", got {other:?}",
                layer.store.display()
            ),
        };
        let bounds = page_bounds(&store);
        Ok(Horizon {
            ds,
            pyramid: store.pyramid().clone(),
            to_world: h.transform,
            // Linear RGB, as `render.background` and the configs say (it had been decoded as
            // gamma 2.2, so a horizon of the background's colour came out darker than it).
            color: layer.color.map(|c| c.clamp(0.0, 1.0) as f32),
            depth_map,
            attribute,
            opacity: layer.opacity as f32,
            boxes: crate::horizon::tile_boxes(store.pyramid(), &bounds),
            bounds,
            store,
        })
    }
}

/// Padding of the data bounds that gives the scene region.
pub const SCENE_PADDING: f64 = 1e-3;

/// All data sets of a scene (volumes first, then horizons, numbered in that order).
pub struct SceneData {
    /// Volumes.
    pub volumes: Vec<Volume>,
    /// Horizons.
    pub horizons: Vec<Horizon>,
}

impl SceneData {
    /// Opens every store of the scene.
    pub fn open(scene: &Scene) -> Result<Self> {
        let n = scene.volumes.len() + scene.horizons.len();
        if n == 0 {
            bail!("the scene has no [[volume]] and no [[horizon]]: nothing to render");
        }
        if n > u16::MAX as usize {
            bail!("too many data sets ({n})");
        }
        let volumes = scene
            .volumes
            .iter()
            .enumerate()
            .map(|(i, v)| Volume::open(v, i as u16))
            .collect::<Result<Vec<_>>>()?;
        let nv = volumes.len();
        let horizons = scene
            .horizons
            .iter()
            .enumerate()
            .map(|(i, h)| Horizon::open(h, (nv + i) as u16, nv))
            .collect::<Result<Vec<_>>>()?;
        Ok(SceneData { volumes, horizons })
    }

    /// Stores by data-set number.
    pub fn stores(&self) -> Vec<Arc<PageStore>> {
        self.volumes
            .iter()
            .map(|v| v.store.clone())
            .chain(self.horizons.iter().map(|h| h.store.clone()))
            .collect()
    }

    /// The pyramid of data set `ds`.
    pub fn pyramid(&self, ds: u16) -> &Pyramid {
        let nv = self.volumes.len();
        if (ds as usize) < nv {
            &self.volumes[ds as usize].pyramid
        } else {
            &self.horizons[ds as usize - nv].pyramid
        }
    }

    /// The region that holds the whole scene: the bounds padded so no sample lies on its
    /// faces. The engine clips to it and the coordinator's k-d tree splits it, so both
    /// must take it from here.
    pub fn region(&self) -> Region {
        self.bounds().padded(SCENE_PADDING)
    }

    /// World bounds of every data set (volume boxes, horizon boxes over their height range).
    pub fn bounds(&self) -> Region {
        let mut r: Option<Region> = None;
        let mut add = |a: &Affine3, lo: [f64; 3], hi: [f64; 3]| {
            for c in 0..8 {
                let p = [0, 1, 2].map(|k| if c >> k & 1 == 0 { lo[k] } else { hi[k] });
                let w = a.apply(p);
                let b = Region { lo: w, hi: w };
                r = Some(match r {
                    Some(r) => r.union(&b),
                    None => b,
                });
            }
        };
        for v in &self.volumes {
            let d = v.dims();
            add(&v.to_world, [-0.5; 3], [0, 1, 2].map(|k| d[k] as f64 - 0.5));
        }
        for h in &self.horizons {
            let d = h.pyramid.level(0).dims;
            let root = h.bounds[h.bounds.len() - 1];
            let (zlo, zhi) = if root[0].is_finite() {
                (root[0] as f64, root[1] as f64)
            } else {
                (0.0, 0.0)
            };
            add(
                &h.to_world,
                [0.0, 0.0, zlo],
                [d[0] as f64 - 1.0, d[1] as f64 - 1.0, zhi],
            );
        }
        r.expect("at least one data set")
    }
}
