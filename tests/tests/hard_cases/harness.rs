//! What every case uses: the backend it runs on (`Ctx`), store and scene builders, and the
//! analytic helpers (lattice counts, slab opacity, ray directions).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use strata_common::camera::View;
use strata_common::geo::Affine3;
use strata_common::image::{composite_front_to_back, PartialImage, Rgba};
use strata_common::kd::{KdNode, KdTree};
use strata_common::scene::{Backend as Caster, Camera, RenderSettings, Scene, VolumeLayer};
use strata_common::wire::FrameSource;
use strata_coordinator::cluster::{Cluster, ClusterOptions};
use strata_coordinator::render::composite_choice;
use strata_tests::scenes;
use strata_worker::engine::{Engine, Outcome};
use tempfile::TempDir;

/// Where a case runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    /// The CPU caster in this process, with its SIMD packets where the CPU has AVX2.
    Cpu,
    /// The CPU caster in this process with the scalar march forced (`render.simd = false`).
    Scalar,
    /// The wgpu caster in this process (any adapter, lavapipe included).
    Gpu,
    /// Worker processes (CPU casters) exchanging and compositing pieces, three unless a
    /// case needs another count.
    Distributed,
}

impl Backend {
    pub const ALL: [Backend; 4] = [
        Backend::Cpu,
        Backend::Scalar,
        Backend::Gpu,
        Backend::Distributed,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Backend::Cpu => "cpu",
            Backend::Scalar => "cpu-scalar",
            Backend::Gpu => "gpu",
            Backend::Distributed => "distributed",
        }
    }
}

/// Workers of the distributed backend.
pub const WORKERS: usize = 3;

/// A case's view of its backend, with a scratch folder of its own.
pub struct Ctx {
    pub backend: Backend,
    /// The backend stops long shader loops (llvmpipe): a case with `long_rays` keeps its
    /// rays under 16 000 samples.
    pub short_loops: bool,
    dir: TempDir,
    rt: Arc<tokio::runtime::Runtime>,
}

pub type Res<T> = Result<T, String>;

fn msg(e: impl std::fmt::Display) -> String {
    format!("{e:#}")
}

impl Ctx {
    pub fn new(backend: Backend, rt: Arc<tokio::runtime::Runtime>) -> Self {
        Ctx {
            backend,
            short_loops: false,
            dir: TempDir::new().expect("temporary folder"),
            rt,
        }
    }

    pub fn dir(&self) -> &Path {
        self.dir.path()
    }

    /// Renders the whole scene on this backend (distributed: over `WORKERS` workers), which
    /// must converge; the image is checked for NaN/Inf and out-of-range values.
    pub fn render(&self, s: &Scene) -> Res<Vec<Rgba>> {
        let (img, converged) = self.render_any(s)?;
        if !converged {
            return Err("the render did not converge".into());
        }
        Ok(img)
    }

    /// Like `render`, also when the engine stops short of convergence (`atlas-full`,
    /// `round-limit`); returns whether it converged.
    pub fn render_any(&self, s: &Scene) -> Res<(Vec<Rgba>, bool)> {
        let r = match self.backend {
            Backend::Distributed => self.distributed(s, WORKERS)?,
            _ => {
                let s = self.on_caster(s);
                let tree = KdTree::single(scenes::scene_region(&s));
                in_process(&s, &tree)?
            }
        };
        clean(&r.0)?;
        Ok(r)
    }

    /// The scene rendered as separate regions and composited front to back: in process, one
    /// engine per leaf of `tree` (as workers would); distributed, over one worker per leaf
    /// (the coordinator's own decomposition).
    pub fn render_regions(&self, s: &Scene, tree: &KdTree) -> Res<Vec<Rgba>> {
        let (img, converged) = match self.backend {
            Backend::Distributed => self.distributed(s, tree.leaves.len())?,
            _ => in_process(&self.on_caster(s), tree)?,
        };
        if !converged {
            return Err("a region's render did not converge".into());
        }
        clean(&img)?;
        Ok(img)
    }

    /// What an invariant "split equals whole" compares against: this backend's whole
    /// render in process, and for the distributed backend the in-process CPU image.
    pub fn whole_reference(&self, s: &Scene) -> Res<Vec<Rgba>> {
        match self.backend {
            Backend::Distributed => {
                let s = scenes::on_backend(s, Caster::Cpu);
                let (img, ok) = in_process(&s, &KdTree::single(scenes::scene_region(&s)))?;
                if !ok {
                    return Err("the in-process reference did not converge".into());
                }
                Ok(img)
            }
            _ => self.render(s),
        }
    }

    pub fn in_process(&self) -> bool {
        self.backend != Backend::Distributed
    }

    fn on_caster(&self, s: &Scene) -> Scene {
        let mut s = s.clone();
        match self.backend {
            Backend::Cpu | Backend::Distributed => s.render.backend = Caster::Cpu,
            Backend::Scalar => {
                s.render.backend = Caster::Cpu;
                s.render.simd = false;
            }
            Backend::Gpu => s.render.backend = Caster::Gpu,
        }
        s
    }

    fn distributed(&self, s: &Scene, workers: usize) -> Res<(Vec<Rgba>, bool)> {
        let mut s = self.on_caster(s);
        s.cluster.frame_timeout_s = 120.0;
        s.cluster.connect_timeout_s = 60.0;
        let mut opts = ClusterOptions::from_scene(&s, Some(workers)).map_err(msg)?;
        opts.worker_exe = Some(PathBuf::from(env!("CARGO_BIN_EXE_strata-test-worker")));
        opts.worker_threads = 1;
        let choice = composite_choice(&s, workers).map_err(msg)?;
        let camera = s.camera.clone().ok_or("the case's scene has no camera")?;
        let (w, h) = (s.render.width, s.render.height);
        let r = self.rt.block_on(async {
            let mut c = Cluster::start(&s, opts).await?;
            let r = c.frame(&camera, w, h, &choice, FrameSource::Render).await;
            c.shutdown().await;
            r
        });
        let r = r.map_err(msg)?;
        if !r.lost.is_empty() {
            return Err(format!("{} worker(s) lost", r.lost.len()));
        }
        let converged = r.stats.iter().all(|st| st.outcome == "converged");
        Ok((r.image.into_vec(), converged))
    }
}

/// Renders each leaf of `tree` with its own engine and composites them in visibility order.
fn in_process(s: &Scene, tree: &KdTree) -> Res<(Vec<Rgba>, bool)> {
    let (w, h) = (s.render.width, s.render.height);
    let mut parts = Vec::new();
    let mut converged = true;
    let mut eye = [0.0; 3];
    for leaf in &tree.leaves {
        let mut e = Engine::new(s).map_err(msg)?;
        let view = e.view(w, h).map_err(msg)?;
        eye = e.camera().eye;
        let r = e.render_batch(&view, leaf).map_err(msg)?;
        converged &= r.outcome == Outcome::Converged;
        parts.push(r.image);
    }
    if parts.len() == 1 {
        return Ok((parts.pop().unwrap().to_full(), converged));
    }
    let order = tree.visibility_order(eye);
    let ordered: Vec<&PartialImage> = order.iter().map(|&i| &parts[i]).collect();
    Ok((composite_front_to_back(w, h, &ordered), converged))
}

/// The rule every case shares: no NaN or Inf, alpha in [0, 1], premultiplied colour in
/// [0, alpha] (up to rounding).
pub fn clean(px: &[Rgba]) -> Res<()> {
    for (i, p) in px.iter().enumerate() {
        let bad = !p.iter().all(|v| v.is_finite())
            || !(0.0..=1.0).contains(&p[3])
            || (0..3).any(|c| p[c] < 0.0 || p[c] > p[3] + 1e-5);
        if bad {
            return Err(format!("pixel {i} is {p:?}"));
        }
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------
// Stores and scenes.

/// An f32 volume store of `dims` samples from `f(i, j, k)`.
pub fn volume(
    ctx: &Ctx,
    name: &str,
    dims: [u64; 3],
    transform: Affine3,
    page: u32,
    f: impl Fn(u64, u64, u64) -> f32,
) -> PathBuf {
    let mut data = Vec::with_capacity((dims[0] * dims[1] * dims[2]) as usize);
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                data.push(f(i, j, k));
            }
        }
    }
    scenes::volume_store(ctx.dir(), name, dims, data, transform, page)
}

/// A horizon store of `dims` heights from `f(i, j)` (NaN = hole).
pub fn horizon(
    ctx: &Ctx,
    name: &str,
    dims: [u64; 2],
    transform: Affine3,
    f: impl Fn(u64, u64) -> f32,
) -> PathBuf {
    let h: Vec<f32> = (0..dims[0] * dims[1])
        .map(|i| f(i % dims[0], i / dims[0]))
        .collect();
    scenes::horizon_store(ctx.dir(), name, dims, h, transform, 16)
}

/// A smooth field with values in about [-1, 1].
pub fn smooth(i: u64, j: u64, k: u64) -> f32 {
    let (x, y, z) = (i as f32, j as f32, k as f32);
    (0.21 * x + 0.1).sin() * (0.17 * y).cos() * 0.7 + 0.3 * (0.13 * z + 0.4).sin()
}

/// A grey layer of constant opacity `a` (per voxel) over `window`: the colour at value v is
/// the grey level (v − lo)/(hi − lo) in linear light.
pub fn grey(store: PathBuf, window: [f64; 2], a: f64) -> VolumeLayer {
    scenes::volume_layer(store, "grey", window, vec![[0.0, a], [1.0, a]])
}

/// A seismic-coloured layer, translucent around zero and more opaque at the extremes.
pub fn seismic(store: PathBuf, window: [f64; 2]) -> VolumeLayer {
    scenes::volume_layer(
        store,
        "seismic",
        window,
        vec![[0.0, 0.25], [0.5, 0.02], [1.0, 0.25]],
    )
}

/// A seismic-coloured 32³-sample volume seen obliquely from outside, 48×40.
pub fn oblique(store: PathBuf) -> Scene {
    scene(
        vec![seismic(store, [-1.0, 1.0])],
        vec![],
        oblique_camera(),
        settings(48, 40),
    )
}

/// Looking down +z at the centre of a 32×32 face from 50 units away, 15° field of view.
pub fn head_on_camera() -> Camera {
    camera(
        [15.5, 15.5, -50.0],
        [15.5, 15.5, 0.0],
        [0.0, 1.0, 0.0],
        15.0,
    )
}

/// Looking at the centre of a 32³ volume from above one corner, 40° field of view.
pub fn oblique_camera() -> Camera {
    camera(
        [-20.0, -35.0, 45.0],
        [15.5, 15.5, 15.5],
        [0.0, 0.0, 1.0],
        40.0,
    )
}

/// A volume of `smooth` samples in pages of `page` samples.
pub fn smooth_volume(ctx: &Ctx, dims: [u64; 3], page: u32) -> PathBuf {
    volume(
        ctx,
        &format!("smooth-{page}"),
        dims,
        Affine3::IDENTITY,
        page,
        smooth,
    )
}

pub fn camera(eye: [f64; 3], target: [f64; 3], up: [f64; 3], fov_deg: f64) -> Camera {
    Camera {
        eye,
        target,
        up,
        fov_deg,
    }
}

/// Exact settings: z up, no early termination, fixed step 1, finest level, no lighting.
pub fn settings(w: u32, h: u32) -> RenderSettings {
    let mut r = scenes::exact_settings(w, h);
    r.adaptive_step = false;
    r.lighting = false;
    r.tau = 1e-6;
    r
}

pub fn scene(
    volumes: Vec<VolumeLayer>,
    horizons: Vec<strata_common::scene::HorizonLayer>,
    camera: Camera,
    render: RenderSettings,
) -> Scene {
    scenes::scene(volumes, horizons, camera, render)
}

pub fn scale_translate(s: [f64; 3], t: [f64; 3]) -> Affine3 {
    Affine3 {
        rows: [
            [s[0], 0.0, 0.0, t[0]],
            [0.0, s[1], 0.0, t[1]],
            [0.0, 0.0, s[2], t[2]],
        ],
    }
}

pub fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

// ---------------------------------------------------------------------------------------
// Analytic helpers.

pub use strata_tests::scenes::lattice_count;

/// Opacity of `n` samples `step` apart through a medium of opacity `a` per voxel.
pub fn slab(a: f64, step: f64, n: u64) -> f64 {
    1.0 - (1.0 - a).powf(step * n as f64)
}

/// Whether `t` lies within `eps` of a lattice point `k·dt` (the count is then ambiguous).
pub fn near_lattice(t: f64, dt: f64, eps: f64) -> bool {
    let r = t / dt;
    (r - r.round()).abs() * dt < eps
}

pub fn view(s: &Scene) -> View {
    View::new(
        s.camera.as_ref().unwrap(),
        &s.render,
        s.render.width,
        s.render.height,
    )
    .unwrap()
}

/// The unit direction of pixel (x, y) (exact settings: display space is world space).
pub fn dir(v: &View, x: u32, y: u32) -> [f64; 3] {
    v.ray_dir(x, y).map(|c| c as f64)
}

pub fn at(img: &[Rgba], w: u32, x: u32, y: u32) -> Rgba {
    img[(y * w + x) as usize]
}

/// Largest channel difference from an expected premultiplied value.
pub fn err4(got: Rgba, want: [f64; 4]) -> f64 {
    (0..4)
        .map(|c| (got[c] as f64 - want[c]).abs())
        .fold(0.0, f64::max)
}

/// Largest channel difference between two images.
pub fn diff(a: &[Rgba], b: &[Rgba]) -> Res<f64> {
    if a.len() != b.len() {
        return Err(format!("image sizes differ: {} and {}", a.len(), b.len()));
    }
    Ok(scenes::max_diff(a, b) as f64)
}

/// The largest alpha of an image (to show that a comparison is not between two empty
/// images).
pub fn max_alpha(img: &[Rgba]) -> f32 {
    img.iter().map(|p| p[3]).fold(0.0, f32::max)
}

/// Fails unless the image shows something (alpha above `min` somewhere).
pub fn shows(img: &[Rgba], min: f32, what: &str) -> Res<()> {
    if max_alpha(img) > min {
        Ok(())
    } else {
        Err(format!(
            "{what}: nothing visible (max alpha {})",
            max_alpha(img)
        ))
    }
}

/// The coordinator's k-d decomposition of `s` over `workers` (what the distributed
/// backend will use), as a tree for the in-process backends.
pub fn decomposition(s: &Scene, workers: usize) -> Res<KdTree> {
    let d = strata_coordinator::decompose::decompose(s, workers, 1).map_err(msg)?;
    Ok(d.tree)
}

/// The split planes of a tree, `(axis, position)`, root first.
pub fn planes(t: &KdTree) -> Vec<(usize, f64)> {
    fn walk(n: &KdNode, out: &mut Vec<(usize, f64)>) {
        if let KdNode::Split { axis, pos, lo, hi } = n {
            out.push((*axis, *pos));
            walk(lo, out);
            walk(hi, out);
        }
    }
    let mut out = Vec::new();
    walk(&t.root, &mut out);
    out
}

/// Largest error of a grey image (colour `g` in linear light) of a constant medium of
/// opacity `a` per voxel filling the box `[-0.5, hi[0]] × [-0.5, hi[1]] × [z[0], z[1])`,
/// seen by rays travelling +z: per pixel, `1-(1-a)^(Δs·n)` with `n` the lattice samples
/// between the ray's entry and exit. Pixels whose ray passes within half a voxel of a side
/// face, or whose entry or exit lies within 1e-3 of a lattice point, are left out; at least
/// `min_pixels` must be checked.
pub fn slab_error(
    s: &Scene,
    img: &[Rgba],
    a: f64,
    z: [f64; 2],
    hi: [f64; 2],
    g: f64,
    min_pixels: usize,
) -> Res<f64> {
    let step = s.render.step;
    let v = view(s);
    let e = s.camera.as_ref().unwrap().eye;
    let (w, h) = (s.render.width, s.render.height);
    let mut err = 0.0f64;
    let mut checked = 0;
    for y in 0..h {
        for x in 0..w {
            let d = dir(&v, x, y);
            if d[2] <= 0.0 {
                continue;
            }
            let (t0, t1) = ((z[0] - e[2]) / d[2], (z[1] - e[2]) / d[2]);
            let inside = |t: f64| {
                (0..2).all(|k| {
                    let c = e[k] + t * d[k];
                    c > 0.0 && c < hi[k] - 0.5
                })
            };
            if !inside(t0)
                || !inside(t1)
                || near_lattice(t0, step, 1e-3)
                || near_lattice(t1, step, 1e-3)
            {
                continue;
            }
            let n = lattice_count(t0.max(0.0) as f32, t1 as f32, step as f32);
            let want = slab(a, step, n);
            err = err.max(err4(at(img, w, x, y), [g * want, g * want, g * want, want]));
            checked += 1;
        }
    }
    if checked < min_pixels {
        return Err(format!("only {checked} pixels checked: mis-built"));
    }
    Ok(err)
}
