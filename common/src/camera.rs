//! The view: camera and data transforms in f64, rays in camera-relative f32.
//!
//! World coordinates of a survey are UTM metres (about 6·10⁶), where f32 has a resolution
//! of half a metre. Everything is therefore placed in *display space* in f64 (world with
//! the vertical axis flipped for z-down data and exaggerated by `z_scale`), and then made
//! relative to the eye before it is rounded to f32. A survey at UTM coordinates renders the
//! same as the same survey moved to the origin.

use crate::geo::Affine3;
use crate::kd::Region;
use crate::scene::{Camera, RenderSettings};
use crate::wall::{TileMap, WallGeometry};

/// Why a camera cannot be made into a view.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ViewError {
    /// A zero image dimension.
    #[error("image size must be positive, got {0}×{1}")]
    Size(u32, u32),
    /// Field of view out of range.
    #[error("camera.fov_deg must lie in (0, 179), got {0}")]
    Fov(f64),
    /// Vertical exaggeration not positive.
    #[error("render.z_scale must be positive, got {0}")]
    ZScale(f64),
    /// A camera vector with a NaN or infinite component (`"eye"`, `"target"` or `"up"`).
    #[error("camera.{0} must be three finite numbers")]
    NotFinite(&'static str),
    /// No viewing direction.
    #[error("camera.eye and camera.target coincide")]
    EyeIsTarget,
    /// No image orientation.
    #[error("camera.up is parallel to the viewing direction")]
    UpParallel,
    /// A wall layout out of range.
    #[error("{0}")]
    Wall(String),
    /// Pixels narrower than f32 ray directions resolve.
    #[error(
        "camera.fov_deg = {fov} over {height} pixels makes pixels of {pixel:.2e} rad, finer \
         than the casters' f32 ray directions resolve ({MIN_PIXEL_ANGLE:.2e} rad: neighbouring \
         pixels would share rays); at this height use at least {min_fov:.3}°"
    )]
    TooNarrow {
        /// The field of view asked for.
        fov: f64,
        /// Image (or wall plane) height in pixels.
        height: u32,
        /// Its pixel angle.
        pixel: f64,
        /// The narrowest field of view this height allows.
        min_fov: f64,
    },
}

/// Narrowest pixel a view may have, in radians: a ray direction is summed in f32 from unit
/// vectors (`dir00 + x·du + y·dv`), so it carries about 6·10⁻⁸ rad of rounding; pixels of
/// 2⁻²⁰ rad keep that under a sixteenth of a pixel. (1920×1080: fov_deg ≥ 0.06.)
pub const MIN_PIXEL_ANGLE: f64 = 1.0 / 1_048_576.0;

/// Display-space transform of world points: `(x, y, ±z · z_scale)`.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct DisplayMap {
    /// Multiplier of world z (negative when z grows downward).
    pub zmul: f64,
}

impl DisplayMap {
    /// From the render settings.
    pub fn new(r: &RenderSettings) -> Self {
        DisplayMap {
            zmul: if r.z_down { -r.z_scale } else { r.z_scale },
        }
    }
    /// World point to display space.
    pub fn apply(&self, p: [f64; 3]) -> [f64; 3] {
        [p[0], p[1], p[2] * self.zmul]
    }
    /// World direction to display space.
    pub fn apply_dir(&self, d: [f64; 3]) -> [f64; 3] {
        [d[0], d[1], d[2] * self.zmul]
    }
    /// An index→world affine composed with the display map.
    pub fn affine(&self, a: &Affine3) -> Affine3 {
        let mut r = *a;
        for c in 0..4 {
            r.rows[2][c] *= self.zmul;
        }
        r
    }
    /// A world region in display space (corners re-sorted when z is flipped).
    pub fn region(&self, r: &Region) -> ([f64; 3], [f64; 3]) {
        let a = self.apply(r.lo);
        let b = self.apply(r.hi);
        if self.zmul < 0.0 {
            // Flipping z swaps the z corners. Sibling regions still share their split plane
            // exactly, which is all the half-open t clipping needs (see `clip`).
            ([a[0], a[1], b[2]], [b[0], b[1], a[2]])
        } else {
            (a, b)
        }
    }
}

/// A camera made ready for ray generation.
#[derive(Clone, Debug)]
pub struct View {
    /// Eye in display space (f64).
    pub eye: [f64; 3],
    /// World → display map.
    pub display: DisplayMap,
    /// Image width (of the stacked image, for a wall).
    pub width: u32,
    /// Image height (of the stacked image, for a wall).
    pub height: u32,
    /// Where image pixels lie on the frustum's image plane: the identity for a plain
    /// image, a wall's tiles for [`View::wall`]. `dir00`, `du` and `dv` are of the plane.
    pub tiles: TileMap,
    /// The frustum's image plane in pixels (a wall's mullions included).
    pub plane: (u32, u32),
    /// Angle of one pixel (radians): the footprint of a pixel at distance t is `t·pixel_angle`.
    pub pixel_angle: f32,
    /// Ray direction (unnormalized) through the corner of pixel (0, 0).
    pub dir00: [f32; 3],
    /// Direction increment per column.
    pub du: [f32; 3],
    /// Direction increment per row.
    pub dv: [f32; 3],
    /// Unit forward vector (display space).
    pub forward: [f32; 3],
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn norm(a: [f64; 3]) -> Option<[f64; 3]> {
    let l = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    (l > 0.0 && l.is_finite()).then(|| a.map(|v| v / l))
}

impl View {
    /// Builds the view of `camera` (world coordinates) at `width`×`height`.
    pub fn new(
        camera: &Camera,
        render: &RenderSettings,
        width: u32,
        height: u32,
    ) -> Result<Self, ViewError> {
        if width == 0 || height == 0 {
            return Err(ViewError::Size(width, height));
        }
        if !(camera.fov_deg > 0.0 && camera.fov_deg < 179.0) {
            return Err(ViewError::Fov(camera.fov_deg));
        }
        if !(render.z_scale > 0.0 && render.z_scale.is_finite()) {
            return Err(ViewError::ZScale(render.z_scale));
        }
        for (key, v) in [
            ("eye", camera.eye),
            ("target", camera.target),
            ("up", camera.up),
        ] {
            if !v.iter().all(|c| c.is_finite()) {
                return Err(ViewError::NotFinite(key));
            }
        }
        let display = DisplayMap::new(render);
        let eye = display.apply(camera.eye);
        let target = display.apply(camera.target);
        let up = display.apply_dir(camera.up);
        let f = norm(sub(target, eye)).ok_or(ViewError::EyeIsTarget)?;
        let r = norm(cross(f, up)).ok_or(ViewError::UpParallel)?;
        let u = cross(r, f);
        let tan = (camera.fov_deg.to_radians() / 2.0).tan();
        let pixel = 2.0 * tan / height as f64;
        if pixel < MIN_PIXEL_ANGLE {
            return Err(ViewError::TooNarrow {
                fov: camera.fov_deg,
                height,
                pixel,
                // Rounded up to the thousandth it is printed with, so that it is accepted.
                min_fov: (2.0
                    * (MIN_PIXEL_ANGLE * height as f64 / 2.0).atan().to_degrees()
                    * 1000.0)
                    .ceil()
                    / 1000.0,
            });
        }
        let aspect = width as f64 / height as f64;
        let dir00 = [0, 1, 2].map(|a| f[a] - tan * aspect * r[a] + tan * u[a]);
        let du = [0, 1, 2].map(|a| 2.0 * tan * aspect / width as f64 * r[a]);
        let dv = [0, 1, 2].map(|a| -2.0 * tan / height as f64 * u[a]);
        Ok(View {
            eye,
            display,
            width,
            height,
            tiles: TileMap::plain(width, height),
            plane: (width, height),
            pixel_angle: (2.0 * tan / height as f64) as f32,
            dir00: dir00.map(|v| v as f32),
            du: du.map(|v| v as f32),
            dv: dv.map(|v| v as f32),
            forward: f.map(|v| v as f32),
        })
    }

    /// The view of a powerwall: one frustum over the whole wall, mullions included, whose
    /// image is the stacked tiles without the mullion pixels ([`crate::wall`]).
    pub fn wall(
        camera: &Camera,
        render: &RenderSettings,
        wall: &WallGeometry,
    ) -> Result<Self, ViewError> {
        wall.check().map_err(ViewError::Wall)?;
        let (pw, ph) = wall.plane_size();
        let mut v = View::new(camera, render, pw, ph)?;
        let (w, h) = wall.stacked_size();
        v.width = w;
        v.height = h;
        v.tiles = wall.tile_map();
        Ok(v)
    }

    /// The unit ray direction through the centre of image pixel (x, y), camera-relative.
    #[inline]
    pub fn ray_dir(&self, x: u32, y: u32) -> [f32; 3] {
        let (x, y) = self.tiles.to_plane(x, y);
        let fx = x as f32 + 0.5;
        let fy = y as f32 + 0.5;
        let d = [0, 1, 2].map(|a| self.dir00[a] + fx * self.du[a] + fy * self.dv[a]);
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        d.map(|v| v / l)
    }

    /// A world point relative to the eye, in display space (f64 subtraction, then f32).
    pub fn relative(&self, world: [f64; 3]) -> [f32; 3] {
        let p = self.display.apply(world);
        [0, 1, 2].map(|a| (p[a] - self.eye[a]) as f32)
    }

    /// Index → camera-relative affine of a data set (f64 composition, then f32 use).
    pub fn relative_affine(&self, index_to_world: &Affine3) -> Affine3 {
        let mut a = self.display.affine(index_to_world);
        for r in 0..3 {
            a.rows[r][3] -= self.eye[r];
        }
        a
    }
}

impl View {
    /// Where a world point lands on the frustum's image plane, in plane pixels (the centre
    /// of pixel (x, y) is `(x + 0.5, y + 0.5)`), or `None` when it lies behind the eye.
    /// The inverse of [`View::ray_dir`] for plain images.
    pub fn project(&self, world: [f64; 3]) -> Option<(f64, f64)> {
        let p = self.display.apply(world);
        let d = [0, 1, 2].map(|a| p[a] - self.eye[a]);
        let dot =
            |a: [f64; 3], b: [f32; 3]| a[0] * b[0] as f64 + a[1] * b[1] as f64 + a[2] * b[2] as f64;
        let f64s = |v: [f32; 3]| v.map(|c| c as f64);
        let depth = dot(d, self.forward);
        let scale = dot(f64s(self.dir00), self.forward);
        if !(depth > 0.0 && scale > 0.0) {
            return None;
        }
        // `du` and `dv` are perpendicular to each other and to `forward`, so the plane
        // point `d · scale/depth` is `dir00 + fx·du + fy·dv` in that basis.
        let s = scale / depth;
        let w = [0, 1, 2].map(|a| d[a] * s - self.dir00[a] as f64);
        let fx = dot(w, self.du) / dot(f64s(self.du), self.du);
        let fy = dot(w, self.dv) / dot(f64s(self.dv), self.dv);
        Some((fx, fy))
    }
}

/// The on-screen displacements `(dx, dy)`, in plane pixels, from view `a` to view `b` of
/// the points of a 9 × 9 × 9 lattice of `bounds` (corners and faces included) that lie in
/// front of both eyes.
fn lattice_moves(a: &View, b: &View, bounds: &Region) -> Vec<(f64, f64)> {
    const N: usize = 9;
    let mut moves = Vec::with_capacity(N * N * N);
    for i in 0..N {
        for j in 0..N {
            for k in 0..N {
                let t = [i, j, k].map(|v| v as f64 / (N - 1) as f64);
                let p = [0, 1, 2].map(|c| bounds.lo[c] + t[c] * (bounds.hi[c] - bounds.lo[c]));
                if let (Some((ax, ay)), Some((bx, by))) = (a.project(p), b.project(p)) {
                    let (dx, dy) = (bx - ax, by - ay);
                    if dx.hypot(dy).is_finite() {
                        moves.push((dx, dy));
                    }
                }
            }
        }
    }
    moves
}

/// How far, in plane pixels, content inside `bounds` moves on screen from view `a` to
/// view `b`: the `quantile` (0: least, 0.5: median, 1: largest) of the displacements of a
/// 9 × 9 × 9 lattice of the box (corners and faces included), over the points in front of
/// both eyes (0 when there are none). A measure for predictions that are checked
/// afterwards (cross-worker occlusion dilates the last frame's map by it), not a bound: a
/// point between lattice points may move somewhat further.
pub fn screen_motion(a: &View, b: &View, bounds: &Region, quantile: f64) -> f64 {
    let mut moves: Vec<f64> = lattice_moves(a, b, bounds)
        .into_iter()
        .map(|(dx, dy)| dx.hypot(dy))
        .collect();
    if moves.is_empty() {
        return 0.0;
    }
    moves.sort_by(f64::total_cmp);
    let i = (quantile.clamp(0.0, 1.0) * (moves.len() - 1) as f64).round() as usize;
    moves[i]
}

/// The median displacement, in plane pixels `(dx, dy)`, of the points of a 9 × 9 × 9 lattice
/// of `bounds` from view `a` to view `b` (each coordinate's median, over the points in front
/// of both eyes; `(0, 0)` when there are none): where most of the box's content moved on
/// screen. A prediction for what is checked afterwards (cross-worker occlusion shifts the
/// last frame's map by it), not a bound.
pub fn screen_shift(a: &View, b: &View, bounds: &Region) -> (f64, f64) {
    let moves = lattice_moves(a, b, bounds);
    let median = |mut v: Vec<f64>| {
        if v.is_empty() {
            return 0.0;
        }
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    (
        median(moves.iter().map(|m| m.0).collect()),
        median(moves.iter().map(|m| m.1).collect()),
    )
}

/// World up as the display shows it: −z where z grows downward (`render.z_down`), else +z.
/// A camera or camera-path keyframe that names no `up` takes it.
pub fn world_up(render: &RenderSettings) -> [f64; 3] {
    [0.0, 0.0, if render.z_down { -1.0 } else { 1.0 }]
}

/// A camera that frames a world box: from the south-west, above, at 35°.
pub fn default_camera(bounds: &Region, render: &RenderSettings) -> Camera {
    let d = DisplayMap::new(render);
    let lo = d.apply(bounds.lo);
    let hi = d.apply(bounds.hi);
    let c = [0, 1, 2].map(|a| 0.5 * (lo[a] + hi[a]));
    let diag = (0..3)
        .map(|a| (hi[a] - lo[a]).powi(2))
        .sum::<f64>()
        .sqrt()
        .max(1e-9);
    let dir = norm([-0.6, -0.75, 0.55]).unwrap();
    let eye_d = [0, 1, 2].map(|a| c[a] + 1.5 * diag * dir[a]);
    let inv = |p: [f64; 3]| [p[0], p[1], p[2] / d.zmul];
    Camera {
        eye: inv(eye_d),
        target: inv(c),
        up: world_up(render),
        fov_deg: 35.0,
    }
}

/// Frame `i` of `frames` on a circle around the camera's target: the eye turned about the
/// vertical (world z) axis through the target by `i / frames` of a full turn, counter-
/// clockwise seen from above; distance and height are kept, and `up` turns with the eye (a
/// vertical `up`, the usual one, is unchanged; a horizontal one would otherwise come to lie
/// along the view, or, seen from straight above, leave every frame the same). Frame 0 is
/// the camera.
pub fn orbit(camera: &Camera, frames: u32, i: u32) -> Camera {
    let a = std::f64::consts::TAU * i as f64 / frames.max(1) as f64;
    let (s, c) = a.sin_cos();
    let [tx, ty, _] = camera.target;
    let (dx, dy) = (camera.eye[0] - tx, camera.eye[1] - ty);
    let [ux, uy, uz] = camera.up;
    Camera {
        eye: [tx + c * dx - s * dy, ty + s * dx + c * dy, camera.eye[2]],
        up: [c * ux - s * uy, s * ux + c * uy, uz],
        ..camera.clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `up` turns with the orbit: a horizontal `up` never comes to lie along the view, and
    /// seen from straight above the frames turn; a vertical one is kept exactly.
    #[test]
    fn orbit_turns_up_with_the_eye() {
        let r = RenderSettings {
            z_down: false,
            ..Default::default()
        };
        let side = Camera {
            eye: [10.0, 0.0, 0.0],
            target: [0.0; 3],
            up: [0.0, 1.0, 0.0],
            fov_deg: 30.0,
        };
        for i in 0..4 {
            let c = orbit(&side, 4, i);
            View::new(&c, &r, 64, 48).unwrap_or_else(|e| panic!("frame {i}: {e}"));
        }
        let above = Camera {
            eye: [0.0, 0.0, 10.0],
            target: [0.0; 3],
            up: [0.0, 1.0, 0.0],
            fov_deg: 30.0,
        };
        let q = orbit(&above, 4, 1);
        assert!(
            (q.up[0] + 1.0).abs() < 1e-12 && q.up[1].abs() < 1e-12,
            "{:?}",
            q.up
        );
        let vertical = Camera {
            up: [0.0, 0.0, 1.0],
            ..side.clone()
        };
        assert_eq!(orbit(&vertical, 7, 3).up, [0.0, 0.0, 1.0]);
    }

    /// A camera above a survey's corner looking at its middle, and the survey's box.
    fn survey_camera() -> (Camera, Region) {
        let cam = Camera {
            eye: [590_000.0, 6_060_000.0, -3000.0],
            target: [605_000.0, 6_075_000.0, 600.0],
            up: [0.0, 0.0, -1.0],
            fov_deg: 35.0,
        };
        let bounds = Region {
            lo: [600_000.0, 6_070_000.0, 0.0],
            hi: [610_000.0, 6_080_000.0, 1200.0],
        };
        (cam, bounds)
    }

    fn demo_view(cam: &Camera) -> View {
        let render = RenderSettings {
            z_scale: 4.0,
            z_down: true,
            ..RenderSettings::default()
        };
        View::new(cam, &render, 320, 180).unwrap()
    }

    #[test]
    fn project_inverts_ray_dir() {
        let cam = Camera {
            eye: [605_100.0, 6_075_000.0, -900.0],
            target: [605_000.0, 6_076_000.0, 1500.0],
            up: [0.0, 0.0, -1.0],
            fov_deg: 35.0,
        };
        let v = demo_view(&cam);
        for (x, y) in [(0, 0), (319, 179), (17, 101), (160, 90)] {
            let d = v.ray_dir(x, y);
            for dist in [10.0, 2500.0] {
                // A display-space point along the ray, back in world coordinates.
                let p = [0, 1, 2].map(|a| v.eye[a] + dist * d[a] as f64);
                let world = [p[0], p[1], p[2] / v.display.zmul];
                let (fx, fy) = v.project(world).unwrap();
                assert!(
                    (fx - (x as f64 + 0.5)).abs() < 1e-3 && (fy - (y as f64 + 0.5)).abs() < 1e-3,
                    "pixel ({x}, {y}) at {dist}: projected to ({fx}, {fy})"
                );
            }
        }
        // Behind the eye.
        let d = v.forward;
        let p = [0, 1, 2].map(|a| v.eye[a] - 100.0 * d[a] as f64);
        assert_eq!(v.project([p[0], p[1], p[2] / v.display.zmul]), None);
    }

    #[test]
    fn screen_motion_grows_with_the_turn_and_is_zero_without_one() {
        let (cam, bounds) = survey_camera();
        let a = demo_view(&cam);
        assert_eq!(screen_motion(&a, &a, &bounds, 1.0), 0.0);
        let one = screen_motion(&a, &demo_view(&orbit(&cam, 120, 1)), &bounds, 1.0);
        let two = screen_motion(&a, &demo_view(&orbit(&cam, 120, 2)), &bounds, 1.0);
        assert!(
            one > 1.0 && two > 1.8 * one && two < 2.2 * one,
            "{one} {two}"
        );
        let median = screen_motion(&a, &demo_view(&orbit(&cam, 120, 1)), &bounds, 0.5);
        let least = screen_motion(&a, &demo_view(&orbit(&cam, 120, 1)), &bounds, 0.0);
        assert!(least <= median && median < one, "{least} {median} {one}");
        // No box corner moves further than the measure says.
        let b = demo_view(&orbit(&cam, 120, 1));
        for c in 0..8 {
            let p = [0, 1, 2].map(|a| {
                if c >> a & 1 == 0 {
                    bounds.lo[a]
                } else {
                    bounds.hi[a]
                }
            });
            let (ax, ay) = a.project(p).unwrap();
            let (bx, by) = b.project(p).unwrap();
            assert!((bx - ax).hypot(by - ay) <= one + 1e-9);
        }
    }

    #[test]
    fn screen_shift_is_the_median_displacement_and_zero_without_motion() {
        let (cam, bounds) = survey_camera();
        let a = demo_view(&cam);
        assert_eq!(screen_shift(&a, &a, &bounds), (0.0, 0.0));
        // A box's centre moves as the box does: the shift of a small box round a point is
        // that point's displacement, wherever the point lies.
        let b = demo_view(&orbit(&cam, 120, 1));
        for p in [
            [605_000.0, 6_075_000.0, 600.0],
            [601_000.0, 6_071_000.0, 100.0],
            [609_000.0, 6_072_000.0, 1100.0],
        ] {
            let small = Region {
                lo: p.map(|v| v - 1.0),
                hi: p.map(|v| v + 1.0),
            };
            let (dx, dy) = screen_shift(&a, &b, &small);
            let (ax, ay) = a.project(p).unwrap();
            let (bx, by) = b.project(p).unwrap();
            assert!(
                (dx - (bx - ax)).abs() < 0.05 && (dy - (by - ay)).abs() < 0.05,
                "{p:?}: {dx} {dy} against {} {}",
                bx - ax,
                by - ay
            );
        }
        // The box's corner eighth nearest the eye (a worker's region at p = 8): it moves
        // by no more than its fastest point, and back the other way when the camera turns
        // back. (The whole box, turning about its middle, barely moves at the median.)
        let near = Region {
            lo: bounds.lo,
            hi: [0, 1, 2].map(|c| (bounds.lo[c] + bounds.hi[c]) / 2.0),
        };
        let (dx, dy) = screen_shift(&a, &b, &near);
        let most = screen_motion(&a, &b, &near, 1.0);
        assert!(
            dx.hypot(dy) > 1.0 && dx.hypot(dy) <= most,
            "{dx} {dy} {most}"
        );
        let back = demo_view(&orbit(&cam, 120, 119));
        let (ex, ey) = screen_shift(&a, &back, &near);
        assert!(
            (ex + dx).abs() < 0.2 * dx.abs() + 0.5 && (ey + dy).abs() < 0.2 * dy.abs() + 0.5,
            "{dx} {dy} / {ex} {ey}"
        );
    }

    #[test]
    fn orbit_turns_the_eye_about_the_target() {
        let cam = Camera {
            eye: [605_100.0, 6_075_000.0, 900.0],
            target: [605_000.0, 6_075_000.0, 1500.0],
            up: [0.0, 0.0, -1.0],
            fov_deg: 35.0,
        };
        assert_eq!(orbit(&cam, 8, 0), cam);
        let quarter = orbit(&cam, 4, 1);
        assert!(
            (quarter.eye[0] - 605_000.0).abs() < 1e-6,
            "{:?}",
            quarter.eye
        );
        assert!(
            (quarter.eye[1] - 6_075_100.0).abs() < 1e-6,
            "{:?}",
            quarter.eye
        );
        assert_eq!(quarter.eye[2], 900.0);
        assert_eq!((quarter.target, quarter.up), (cam.target, cam.up));
        for i in 0..7 {
            let e = orbit(&cam, 7, i).eye;
            let r = ((e[0] - 605_000.0).powi(2) + (e[1] - 6_075_000.0).powi(2)).sqrt();
            assert!((r - 100.0).abs() < 1e-6, "frame {i}: radius {r}");
        }
    }

    #[test]
    fn centre_ray_is_forward_and_not_mirrored() {
        let cam = Camera {
            eye: [0.0, -10.0, 0.0],
            target: [0.0, 0.0, 0.0],
            up: [0.0, 0.0, 1.0],
            fov_deg: 40.0,
        };
        let r = RenderSettings {
            z_down: false,
            ..RenderSettings::default()
        };
        let v = View::new(&cam, &r, 101, 51).unwrap();
        let d = v.ray_dir(50, 25);
        assert!((d[1] - 1.0).abs() < 1e-6, "{d:?}");
        // Looking north with z up, east (+x) is on the right of the image.
        assert!(v.ray_dir(100, 25)[0] > 0.0);
        // and up (+z) at the top.
        assert!(v.ray_dir(50, 0)[2] > 0.0);
        // z-down data: the same camera in a z-down world still puts east on the right.
        let r = RenderSettings::default();
        let cam = Camera {
            up: [0.0, 0.0, -1.0],
            ..cam
        };
        let v = View::new(&cam, &r, 101, 51).unwrap();
        assert!(v.ray_dir(100, 25)[0] > 0.0);
    }

    #[test]
    fn wall_rays_are_the_plane_rays_of_their_tiles() {
        let cam = Camera {
            eye: [3.0, -10.0, 2.0],
            target: [0.0, 0.0, 0.0],
            up: [0.0, 0.0, -1.0],
            fov_deg: 50.0,
        };
        let r = RenderSettings::default();
        let g = WallGeometry {
            cols: 3,
            rows: 2,
            tile_w: 7,
            tile_h: 5,
            mullion_x: 2,
            mullion_y: 3,
        };
        let wall = View::wall(&cam, &r, &g).unwrap();
        let (pw, ph) = g.plane_size();
        let plane = View::new(&cam, &r, pw, ph).unwrap();
        assert_eq!((wall.width, wall.height), (7, 30));
        assert_eq!(wall.plane, (pw, ph));
        assert_eq!(wall.pixel_angle, plane.pixel_angle);
        for t in 0..6 {
            let (ox, oy) = g.tile_origin(t);
            for y in 0..5 {
                for x in 0..7 {
                    assert_eq!(
                        wall.ray_dir(x, t * 5 + y),
                        plane.ray_dir(ox + x, oy + y),
                        "tile {t} ({x}, {y})"
                    );
                }
            }
        }
        let bad = WallGeometry { cols: 0, ..g };
        assert!(matches!(
            View::wall(&cam, &r, &bad),
            Err(ViewError::Wall(_))
        ));
    }
}
