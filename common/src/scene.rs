//! The scene description: which stores to draw, how, and from where.
//!
//! Scenes are TOML. Parse errors name the file, line and column (the `toml` crate's spans).
//! Store paths are relative to the scene file's folder. This is the part of the scene model
//! that the data layer needs; the renderer adds camera and transfer-function detail.

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// A whole scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Volumes (seismic cubes, CT, ...).
    #[serde(default, rename = "volume")]
    pub volumes: Vec<VolumeLayer>,
    /// Horizons.
    #[serde(default, rename = "horizon")]
    pub horizons: Vec<HorizonLayer>,
    /// Camera; the renderer frames the scene if absent.
    #[serde(default)]
    pub camera: Option<Camera>,
    /// Render settings.
    #[serde(default)]
    pub render: RenderSettings,
}

/// A volume to draw.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VolumeLayer {
    /// Page-store file.
    pub store: PathBuf,
    /// Colour map name (e.g. "seismic", "grey").
    #[serde(default = "default_colormap")]
    pub colormap: String,
    /// Value window mapped onto the colour map; the store's range if absent.
    #[serde(default)]
    pub window: Option<[f64; 2]>,
    /// Opacity scale.
    #[serde(default = "one")]
    pub opacity: f64,
}

/// A horizon to draw.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HorizonLayer {
    /// Page-store file.
    pub store: PathBuf,
    /// RGB colour in 0..1.
    #[serde(default = "default_color")]
    pub color: [f64; 3],
    /// Opacity in 0..1.
    #[serde(default = "one")]
    pub opacity: f64,
}

/// A pinhole camera in world coordinates (f64).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    /// Eye position.
    pub eye: [f64; 3],
    /// Point looked at.
    pub target: [f64; 3],
    /// Up direction.
    #[serde(default = "default_up")]
    pub up: [f64; 3],
    /// Vertical field of view in degrees.
    #[serde(default = "default_fov")]
    pub fov_deg: f64,
}

/// Render settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderSettings {
    /// Image width.
    #[serde(default = "default_w")]
    pub width: u32,
    /// Image height.
    #[serde(default = "default_h")]
    pub height: u32,
    /// Host page-cache budget in MiB.
    #[serde(default = "default_cache")]
    pub cache_mb: u64,
    /// World units per unit of z (vertical exaggeration of time or depth axes).
    #[serde(default = "one")]
    pub z_scale: f64,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            width: default_w(),
            height: default_h(),
            cache_mb: default_cache(),
            z_scale: 1.0,
        }
    }
}

fn default_colormap() -> String {
    "seismic".into()
}
fn default_color() -> [f64; 3] {
    [0.9, 0.8, 0.3]
}
fn default_up() -> [f64; 3] {
    [0.0, 0.0, -1.0]
}
fn default_fov() -> f64 {
    35.0
}
fn default_w() -> u32 {
    1280
}
fn default_h() -> u32 {
    720
}
fn default_cache() -> u64 {
    1024
}
fn one() -> f64 {
    1.0
}

/// A scene that failed to parse: the message names file, line and column.
#[derive(Debug, thiserror::Error)]
#[error("{path}:{line}:{column}: {message}")]
pub struct SceneError {
    /// The scene file.
    pub path: PathBuf,
    /// 1-based line.
    pub line: usize,
    /// 1-based column.
    pub column: usize,
    /// What was wrong.
    pub message: String,
}

impl Scene {
    /// Parses scene text; `path` names the file in errors and anchors relative store paths.
    pub fn parse(path: &Path, text: &str) -> Result<Scene, SceneError> {
        let mut scene: Scene = toml::from_str(text).map_err(|e| {
            let (line, column) = e
                .span()
                .map(|s| {
                    let before = &text[..s.start.min(text.len())];
                    let line = before.matches('\n').count() + 1;
                    let col = before.len() - before.rfind('\n').map_or(0, |i| i + 1) + 1;
                    (line, col)
                })
                .unwrap_or((1, 1));
            SceneError {
                path: path.to_path_buf(),
                line,
                column,
                message: e.message().to_string(),
            }
        })?;
        let base = path.parent().unwrap_or(Path::new("."));
        for v in &mut scene.volumes {
            if v.store.is_relative() {
                v.store = base.join(&v.store);
            }
        }
        for h in &mut scene.horizons {
            if h.store.is_relative() {
                h.store = base.join(&h.store);
            }
        }
        Ok(scene)
    }

    /// Serializes the scene as TOML.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("a scene always serializes")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_resolves_paths() {
        let s = Scene::parse(
            Path::new("/data/survey/scene.toml"),
            "[[volume]]\nstore = \"cube.strata\"\n[[horizon]]\nstore = \"/abs/h.strata\"\n[render]\nwidth = 64\n",
        )
        .unwrap();
        assert_eq!(
            s.volumes[0].store,
            PathBuf::from("/data/survey/cube.strata")
        );
        assert_eq!(s.horizons[0].store, PathBuf::from("/abs/h.strata"));
        assert_eq!(s.render.width, 64);
        assert_eq!(s.render.height, 720);
    }

    #[test]
    fn errors_point_at_line_and_column() {
        let e =
            Scene::parse(Path::new("s.toml"), "[render]\nwidth = 64\nheigth = 3\n").unwrap_err();
        assert_eq!((e.line, e.column), (3, 1), "{e}");
        assert!(e.to_string().starts_with("s.toml:3:1:"), "{e}");
        let e = Scene::parse(Path::new("s.toml"), "[render]\nwidth = \"wide\"\n").unwrap_err();
        assert_eq!(e.line, 2, "{e}");
    }

    #[test]
    fn round_trips_through_toml() {
        let s = Scene::parse(
            Path::new("a.toml"),
            "[[volume]]\nstore = \"/c.strata\"\nwindow = [-1.0, 1.0]\n",
        )
        .unwrap();
        let again = Scene::parse(Path::new("a.toml"), &s.to_toml()).unwrap();
        assert_eq!(s, again);
    }
}
