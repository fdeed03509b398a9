//! Camera paths for frame sequences: keyframes of time, eye, target, up and field of view,
//! interpolated linearly or smoothly (Catmull-Rom tangents with ease in/out), sampled at
//! `fps` frames per second. World coordinates are f64, like the scene's.
//!
//! A path file is TOML (or the same fields in JSON):
//!
//! ```toml
//! interpolation = "smooth"   # or "linear"
//! fps = 24
//! [[keyframes]]
//! time = 0.0
//! eye = [605000.0, 6074000.0, -900.0]
//! target = [606000.0, 6075000.0, 1200.0]
//! up = [0.0, 0.0, -1.0]        # default: the world's up as the scene shows it (−z when z grows downward)
//! fov_deg = 35.0               # default 35
//! [[keyframes]]
//! time = 4.0
//! eye = [607000.0, 6074000.0, -900.0]
//! target = [606000.0, 6075000.0, 1200.0]
//! ```

use crate::scene::Camera;
use serde::{Deserialize, Serialize};

/// How keyframes are joined.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Interpolation {
    /// Straight segments at constant speed between keyframes.
    Linear,
    /// A C¹ cubic through the keyframes, each reached at its `time`: Catmull-Rom tangents
    /// (for uneven times) at the inner keyframes, at rest at the first and the last (eased
    /// in and out). The field of view stays between each segment's two keyframes' (a cubic
    /// overshoots a held value).
    #[default]
    Smooth,
}

/// Until [`CameraPath::with_default_up`] says otherwise: −z, up where z grows downward.
fn default_up() -> [f64; 3] {
    [0.0, 0.0, -1.0]
}

fn default_fov() -> f64 {
    35.0
}

fn default_fps() -> f64 {
    24.0
}

/// One keyframe.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Keyframe {
    /// Seconds from the path's start.
    pub time: f64,
    /// Eye (world).
    pub eye: [f64; 3],
    /// Look-at point (world).
    pub target: [f64; 3],
    /// Up direction; absent: the path's default up ([`CameraPath::with_default_up`]: the
    /// scene's world up, −z where z grows downward, +z otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub up: Option<[f64; 3]>,
    /// Vertical field of view, degrees.
    #[serde(default = "default_fov")]
    pub fov_deg: f64,
}

/// A camera path.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraPath {
    /// How keyframes are joined.
    #[serde(default)]
    pub interpolation: Interpolation,
    /// Frames per second of path time.
    #[serde(default = "default_fps")]
    pub fps: f64,
    /// Keyframes, times strictly increasing.
    pub keyframes: Vec<Keyframe>,
    /// The up of keyframes that name none (not in the file: the scene decides it).
    #[serde(skip, default = "default_up")]
    pub default_up: [f64; 3],
}

/// The most frames a path may describe.
pub const MAX_PATH_FRAMES: u64 = 1_000_000;

/// Why a path is unusable.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PathError {
    /// The file does not parse (the message names line and column).
    #[error("{0}")]
    Parse(String),
    /// A value is out of range.
    #[error("{0}")]
    Invalid(String),
}

impl CameraPath {
    /// Parses a TOML path and checks it.
    pub fn from_toml(text: &str) -> Result<Self, PathError> {
        let p: CameraPath = toml::from_str(text).map_err(|e| PathError::Parse(e.to_string()))?;
        p.check()?;
        Ok(p)
    }

    /// Checks the values: at least one keyframe, strictly increasing finite times, finite
    /// positions, a field of view in (0, 179), an fps that gives at most
    /// [`MAX_PATH_FRAMES`] frames.
    pub fn check(&self) -> Result<(), PathError> {
        let bad = |m: String| Err(PathError::Invalid(m));
        if self.keyframes.is_empty() {
            return bad("a camera path needs at least one [[keyframes]] entry".into());
        }
        if !(self.fps > 0.0 && self.fps.is_finite()) {
            return bad(format!("fps must be a positive number, got {}", self.fps));
        }
        for (i, k) in self.keyframes.iter().enumerate() {
            let finite = k.time.is_finite()
                && k.eye
                    .iter()
                    .chain(&k.target)
                    .chain(k.up.iter().flatten())
                    .all(|v| v.is_finite());
            if !finite {
                return bad(format!("keyframe {i}: every value must be finite"));
            }
            if !(k.fov_deg > 0.0 && k.fov_deg < 179.0) {
                return bad(format!(
                    "keyframe {i}: fov_deg must lie in (0, 179), got {}",
                    k.fov_deg
                ));
            }
            if i > 0 && k.time <= self.keyframes[i - 1].time {
                return bad(format!(
                    "keyframe {i}: time {} does not follow {} (times must increase)",
                    k.time,
                    self.keyframes[i - 1].time
                ));
            }
        }
        let n = self.duration() * self.fps;
        if n >= MAX_PATH_FRAMES as f64 {
            return bad(format!(
                "the path describes {n:.0} frames (duration × fps), more than {MAX_PATH_FRAMES}"
            ));
        }
        Ok(())
    }

    /// Sets the up of keyframes that name none: the scene's world up
    /// (`camera::world_up`).
    pub fn with_default_up(mut self, up: [f64; 3]) -> Self {
        self.default_up = up;
        self
    }

    /// Seconds from the first keyframe to the last.
    pub fn duration(&self) -> f64 {
        self.keyframes.last().map_or(0.0, |l| l.time) - self.keyframes[0].time
    }

    /// Frames of the path: one at each 1/fps from the first keyframe through the last.
    pub fn frame_count(&self) -> u32 {
        (self.duration() * self.fps + 1e-9).floor() as u32 + 1
    }

    /// The camera of frame `i`.
    pub fn frame(&self, i: u32) -> Camera {
        let t = self.keyframes[0].time + i as f64 / self.fps;
        self.at(t.min(self.keyframes.last().expect("checked").time))
    }

    /// The camera at path time `t` (clamped to the keyframes' span).
    pub fn at(&self, t: f64) -> Camera {
        let k = &self.keyframes;
        let up = |f: &Keyframe| f.up.unwrap_or(self.default_up);
        if k.len() == 1 {
            return Camera {
                eye: k[0].eye,
                target: k[0].target,
                up: up(&k[0]),
                fov_deg: k[0].fov_deg,
            };
        }
        let (t0, t1) = (k[0].time, k[k.len() - 1].time);
        let t = t.clamp(t0, t1);
        let s = k.partition_point(|f| f.time <= t).clamp(1, k.len() - 1) - 1;
        let (a, b) = (&k[s], &k[s + 1]);
        let h = b.time - a.time;
        let u = (t - a.time) / h;
        let get = |f: &Keyframe| -> [f64; 10] {
            let up = up(f);
            [
                f.eye[0],
                f.eye[1],
                f.eye[2],
                f.target[0],
                f.target[1],
                f.target[2],
                up[0],
                up[1],
                up[2],
                f.fov_deg,
            ]
        };
        let (pa, pb) = (get(a), get(b));
        let v: [f64; 10] = match self.interpolation {
            Interpolation::Linear => std::array::from_fn(|c| pa[c] + u * (pb[c] - pa[c])),
            Interpolation::Smooth => {
                // Catmull-Rom tangents for uneven keyframe times, as derivatives per unit of
                // path time, scaled to the segment; zero at the ends: the camera starts and
                // stops at rest (the ease in and out), and every keyframe is reached at its
                // time (an ease over the whole path's time had moved them: keyframe 1 of
                // ten evenly spaced came at 1.95 s instead of 1).
                let tangent = |i: usize| -> [f64; 10] {
                    if i == 0 || i == k.len() - 1 {
                        return [0.0; 10];
                    }
                    let (pl, pr) = (get(&k[i - 1]), get(&k[i + 1]));
                    let dt = k[i + 1].time - k[i - 1].time;
                    std::array::from_fn(|c| (pr[c] - pl[c]) / dt)
                };
                let (ma, mb) = (tangent(s), tangent(s + 1));
                let (u2, u3) = (u * u, u * u * u);
                let h00 = 2.0 * u3 - 3.0 * u2 + 1.0;
                let h10 = u3 - 2.0 * u2 + u;
                let h01 = -2.0 * u3 + 3.0 * u2;
                let h11 = u3 - u2;
                let mut v: [f64; 10] = std::array::from_fn(|c| {
                    h00 * pa[c] + h10 * h * ma[c] + h01 * pb[c] + h11 * h * mb[c]
                });
                // The field of view within its segment's keyframes' (checked values): a
                // zoom held after a change would otherwise overshoot, past 179° even.
                v[9] = v[9].clamp(pa[9].min(pb[9]), pa[9].max(pb[9]));
                v
            }
        };
        Camera {
            eye: [v[0], v[1], v[2]],
            target: [v[3], v[4], v[5]],
            up: [v[6], v[7], v[8]],
            fov_deg: v[9],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PATH: &str = r#"
interpolation = "linear"
fps = 2
[[keyframes]]
time = 0.0
eye = [605000.0, 6074000.0, -900.0]
target = [606000.0, 6075000.0, 1200.0]
[[keyframes]]
time = 1.0
eye = [605100.0, 6074000.0, -900.0]
target = [606000.0, 6075000.0, 1200.0]
fov_deg = 45.0
[[keyframes]]
time = 3.0
eye = [605100.0, 6074200.0, -700.0]
target = [606000.0, 6075000.0, 1200.0]
"#;

    #[test]
    fn linear_paths_pass_through_keyframes_at_constant_speed() {
        let p = CameraPath::from_toml(PATH).unwrap();
        assert_eq!(p.frame_count(), 7); // 0, 0.5, …, 3.0 s
        assert_eq!(p.frame(0).eye, [605000.0, 6074000.0, -900.0]);
        assert_eq!(p.frame(1).eye, [605050.0, 6074000.0, -900.0]);
        assert_eq!(p.frame(1).fov_deg, 40.0);
        assert_eq!(p.frame(2).eye, [605100.0, 6074000.0, -900.0]);
        assert_eq!(p.frame(4).eye, [605100.0, 6074100.0, -800.0]);
        assert_eq!(p.frame(6).eye, [605100.0, 6074200.0, -700.0]);
        assert_eq!(
            p.frame(6).up,
            [0.0, 0.0, -1.0],
            "the scene camera's default up"
        );
    }

    #[test]
    fn smooth_paths_hit_the_ends_and_are_continuous() {
        let mut p = CameraPath::from_toml(PATH).unwrap();
        p.interpolation = Interpolation::Smooth;
        let (first, last) = (&p.keyframes[0], &p.keyframes[2]);
        assert_eq!(p.at(0.0).eye, first.eye);
        assert_eq!(p.at(3.0).eye, last.eye);
        // Eased: the camera starts and ends at rest, and moves without jumps in between.
        let step = |t: f64, dt: f64| {
            let (a, b) = (p.at(t).eye, p.at(t + dt).eye);
            (0..3).map(|c| (b[c] - a[c]).powi(2)).sum::<f64>().sqrt()
        };
        assert!(step(0.0, 1e-3) < 1e-3 && step(3.0 - 1e-3, 1e-3) < 1e-3);
        let mut prev = p.at(0.0).eye;
        for i in 1..=3000 {
            let e = p.at(i as f64 * 1e-3).eye;
            let d = (0..3).map(|c| (e[c] - prev[c]).powi(2)).sum::<f64>().sqrt();
            assert!(d < 1.0, "jump of {d} at t = {}", i as f64 * 1e-3);
            prev = e;
        }
    }

    /// Every keyframe is reached at its time, and a zoom held after a change stays within
    /// the keyframes' fields of view (it had overshot to 188° and been refused).
    #[test]
    fn smooth_paths_pass_their_keyframes_at_their_times_without_overshooting_the_zoom() {
        let mut text = String::from("interpolation = \"smooth\"\nfps = 1\n");
        for (i, (t, fov)) in [(0.0, 30.0), (1.0, 170.0), (10.0, 170.0), (12.0, 40.0)]
            .iter()
            .enumerate()
        {
            text += &format!(
                "[[keyframes]]\ntime = {t}\neye = [{}.0, {}.0, 50.0]\ntarget = [0.0, 0.0, 0.0]\nfov_deg = {fov}\n",
                10 * i + 5,
                (i * i) as f64
            );
        }
        let p = CameraPath::from_toml(&text).unwrap();
        for k in &p.keyframes {
            let c = p.at(k.time);
            for a in 0..3 {
                assert!(
                    (c.eye[a] - k.eye[a]).abs() < 1e-9,
                    "t {}: {:?}",
                    k.time,
                    c.eye
                );
            }
            assert!((c.fov_deg - k.fov_deg).abs() < 1e-9);
        }
        for i in 0..=1200 {
            let f = p.at(i as f64 * 0.01).fov_deg;
            assert!(
                (30.0..=170.0).contains(&f),
                "t {}: fov {f}",
                i as f64 * 0.01
            );
        }
    }

    #[test]
    fn bad_paths_name_the_problem() {
        let e = CameraPath::from_toml("fps = 24\nkeyframes = []\n").unwrap_err();
        assert!(e.to_string().contains("at least one"), "{e}");
        let e = CameraPath::from_toml(&PATH.replace("time = 3.0", "time = 0.5")).unwrap_err();
        assert!(e.to_string().contains("keyframe 2"), "{e}");
        let e = CameraPath::from_toml(&PATH.replace("fps = 2", "fps = -1")).unwrap_err();
        assert!(e.to_string().contains("fps"), "{e}");
        let e =
            CameraPath::from_toml(&PATH.replace("fov_deg = 45.0", "fov_deg = 190.0")).unwrap_err();
        assert!(e.to_string().contains("fov_deg"), "{e}");
        // Syntax and unknown keys: the parser's message names the line.
        let e = CameraPath::from_toml(&PATH.replace("fps = 2", "fsp = 2")).unwrap_err();
        assert!(e.to_string().contains("line 3"), "{e}");
        let e = CameraPath::from_toml(&PATH.replace("fps = 2", "fps = 1e9")).unwrap_err();
        assert!(e.to_string().contains("more than"), "{e}");
    }
}
