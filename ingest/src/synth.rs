//! Deterministic synthetic seismic surveys.
//!
//! A layered earth (one reflection coefficient per layer interface) is folded (a sinusoidal
//! anticline/syncline train plus a dome, stronger at depth), cut by a vertical normal fault
//! whose throw dies out along strike, and has one layer that pinches out onto the layer
//! below (so two horizons touch over part of the survey). Each trace is the reflectivity
//! series convolved with a Ricker wavelet, plus a little deterministic noise. Three horizons
//! follow chosen interfaces: the shallow one has holes (an eroded channel and an
//! interpretation gap along the fault), and the other two touch where the layer pinches out.
//!
//! Everything is a pure function of `(seed, size)` and of the trace position, so any box of
//! any size can be generated independently (the builder streams the cube with bounded
//! memory) and the same seed always gives the same bytes.

use crate::builder::{build_store, BuildOptions, BuildReport};
use crate::source::{GridSource, MemorySource};
use anyhow::{Context, Result};
use indicatif::ProgressBar;
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use strata_common::digest::fmix64;
use strata_common::geo::{Affine2, Affine3, SurveyGrid};
use strata_common::sample::SampleType;
use strata_common::scene::{Camera, HorizonLayer, RenderSettings, Scene, VolumeLayer};
use strata_common::store::{Units, VerticalDomain};

/// Sample interval of synthetic traces in milliseconds.
pub const DT_MS: f64 = 4.0;
/// Peak frequency of the Ricker wavelet in Hz.
pub const RICKER_HZ: f64 = 25.0;

/// Vertical exaggeration of the synthetic scene: 4 world units per ms of two-way time.
pub const Z_SCALE: f64 = 4.0;

/// The synthetic earth model for one seed and size.
#[derive(Clone, Debug)]
pub struct SynthModel {
    /// Samples per axis (inline, crossline, time).
    pub dims: [u64; 3],
    seed: u64,
    /// Base depth (samples) of each interface.
    base: Vec<f64>,
    /// Reflection coefficient of each interface.
    refl: Vec<f64>,
    /// Indices of the interfaces the three horizons follow.
    pub horizon_layers: [usize; 3],
    /// The lateral survey grid (UTM, rotated).
    pub survey: SurveyGrid,
}

fn unit(seed: u64, a: u64, b: u64) -> f64 {
    (fmix64(seed ^ fmix64(a.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ fmix64(b))) >> 11) as f64
        / (1u64 << 53) as f64
}

impl SynthModel {
    /// Builds the model. `dims` must be at least 8 samples per axis.
    pub fn new(dims: [u64; 3], seed: u64) -> Result<Self> {
        // The bounds a scene's `[synthetic]` is held to where it is read: they also bound
        // the interfaces below (about one per 6 samples) and what is written (the horizons'
        // grids and the volume) before anything is made.
        strata_common::scene::SyntheticSpec::check_size(dims)
            .map_err(|why| anyhow::anyhow!("synthetic survey {why}"))?;
        let nz = dims[2] as f64;
        let spacing = (nz / 24.0).clamp(6.0, 40.0);
        let mut base = Vec::new();
        let mut refl = Vec::new();
        let mut z = spacing * 0.8;
        let mut n = 0u64;
        // At least four interfaces, which three distinct horizon surfaces need (a thin
        // cube, NZ below about 20, has fewer within it: the rest lie below).
        while z < nz + 0.3 * nz || base.len() < 4 {
            base.push(z);
            let r = unit(seed, 1, n) * 2.0 - 1.0;
            // Every fourth interface is a strong reflector; the rest are weak.
            refl.push(if n % 4 == 1 {
                r.signum() * (0.7 + 0.3 * r.abs())
            } else {
                0.35 * r
            });
            z += spacing * (0.6 + 0.8 * unit(seed, 2, n));
            n += 1;
        }
        let count = base.len();
        let pick = |frac: f64| (frac * nz / spacing) as usize;
        // Distinct layers: h1 < h2 < h2 + 1 < count (count ≥ 4).
        let h1 = pick(0.25).clamp(1, count - 3);
        let h2 = pick(0.55).clamp(h1 + 1, count - 2);
        let horizon_layers = [h1, h2, h2 + 1];
        let (c, s) = (17f64.to_radians().cos(), 17f64.to_radians().sin());
        let survey = SurveyGrid {
            inline0: 1000.0,
            inline_step: 1.0,
            n_inline: dims[0],
            xline0: 2000.0,
            xline_step: 1.0,
            n_xline: dims[1],
            to_world: Affine2 {
                rows: [
                    [25.0 * c, -25.0 * s, 605_000.0],
                    [25.0 * s, 25.0 * c, 6_075_000.0],
                ],
            },
        };
        Ok(SynthModel {
            dims,
            seed,
            base,
            refl,
            horizon_layers,
            survey,
        })
    }

    /// Depth (in samples, fractional) of every interface at trace `(i, j)`, and whether the
    /// trace lies in the fault's interpretation gap or the eroded channel.
    pub fn interfaces(&self, i: f64, j: f64, out: &mut Vec<f64>) {
        let [nx, ny, nz] = self.dims.map(|d| d as f64);
        let (u, v) = (i / nx, j / ny);
        let tau = std::f64::consts::TAU;
        let ph = unit(self.seed, 3, 0) * tau;
        let fold = 0.06 * nz * (tau * 1.5 * u + ph).sin() * (tau * 0.8 * v).cos()
            + 0.10 * nz * (-((u - 0.6).powi(2) + (v - 0.4).powi(2)) / 0.05).exp();
        // Vertical normal fault along a line across the survey; throw tapers out along strike.
        let side = (u - 0.45) * 0.9 + (v - 0.5) * 0.45;
        let throw = if side > 0.0 {
            0.05 * nz * (1.0 - (v - 0.1).clamp(0.0, 1.0)).clamp(0.0, 1.0)
        } else {
            0.0
        };
        out.clear();
        for &b in &self.base {
            let depth_gain = 0.3 + 0.7 * (b / nz).min(1.3);
            out.push(b + fold * depth_gain + throw);
        }
        // Pinch-out: the layer of horizon 2 thins to nothing toward high inlines, so horizons
        // 2 and 3 touch over part of the survey.
        let [_, l2, l3] = self.horizon_layers;
        let thick = out[l3] - out[l2];
        let pinch = (1.0 - ((u - 0.35) / 0.35).clamp(0.0, 1.0)).max(0.0);
        out[l2] = out[l3] - thick * pinch;
        // Keep interfaces ordered (layers never overturn).
        for k in 1..out.len() {
            if out[k] < out[k - 1] {
                out[k] = out[k - 1];
            }
        }
    }

    fn ricker(tau: f64) -> f64 {
        let f = RICKER_HZ * DT_MS / 1000.0; // cycles per sample
        let a = (std::f64::consts::PI * f * tau).powi(2);
        (1.0 - 2.0 * a) * (-a).exp()
    }

    /// Fills `out[k - k0]` for `k` in `k0..k0 + out.len()` with trace `(i, j)`.
    pub fn trace(&self, i: u64, j: u64, k0: u64, out: &mut [f32], scratch: &mut Vec<f64>) {
        self.interfaces(i as f64, j as f64, scratch);
        let support = (2.0 / (RICKER_HZ * DT_MS / 1000.0)).ceil();
        let mut acc = vec![0f64; out.len()];
        let (lo, hi) = (k0 as f64, (k0 + out.len() as u64) as f64);
        for (n, &d) in scratch.iter().enumerate() {
            if d + support < lo || d - support >= hi {
                continue;
            }
            let ks = (d - support).max(lo).ceil() as u64;
            let ke = ((d + support).min(hi - 1.0)).floor() as u64;
            for k in ks..=ke {
                acc[(k - k0) as usize] += self.refl[n] * Self::ricker(k as f64 - d);
            }
        }
        let trace_id = (j << 20) | i;
        for (o, (k, a)) in out.iter_mut().zip(acc.iter().enumerate()) {
            let noise = unit(self.seed, 4 ^ (trace_id << 3), k0 + k as u64) - 0.5;
            *o = (8000.0 * (a + 0.03 * noise)) as f32;
        }
    }

    /// Heights (ms) of the three horizons, inline index fastest; `NaN` = hole.
    pub fn horizon_grids(&self) -> [Vec<f32>; 3] {
        let [nx, ny, _] = self.dims;
        let mut grids = [
            vec![0f32; (nx * ny) as usize],
            vec![0f32; (nx * ny) as usize],
            vec![0f32; (nx * ny) as usize],
        ];
        let rows: Vec<[Vec<f32>; 3]> = (0..ny)
            .into_par_iter()
            .map(|j| {
                let mut s = Vec::new();
                let mut r = [
                    Vec::with_capacity(nx as usize),
                    Vec::with_capacity(nx as usize),
                    Vec::with_capacity(nx as usize),
                ];
                for i in 0..nx {
                    self.interfaces(i as f64, j as f64, &mut s);
                    for (h, &l) in self.horizon_layers.iter().enumerate() {
                        r[h].push((s[l] * DT_MS) as f32);
                    }
                    // Horizon 1: holes along the fault (picks stop at the fault) and in a
                    // sinuous channel that eroded it.
                    let (u, v) = (i as f64 / nx as f64, j as f64 / ny as f64);
                    let side = (u - 0.45) * 0.9 + (v - 0.5) * 0.45;
                    let channel =
                        (u - (0.2 + 0.08 * (std::f64::consts::TAU * 2.0 * v).sin())).abs() < 0.03
                            && v > 0.15;
                    if side.abs() < 1.5 / nx as f64 || channel {
                        *r[0].last_mut().unwrap() = f32::NAN;
                    }
                }
                r
            })
            .collect();
        for (j, r) in rows.into_iter().enumerate() {
            for h in 0..3 {
                grids[h][j * nx as usize..(j + 1) * nx as usize].copy_from_slice(&r[h]);
            }
        }
        grids
    }

    /// Index → world transform of the cube: lateral from the survey grid, z = two-way time in ms.
    pub fn transform(&self) -> Affine3 {
        Affine3::from_lateral(&self.survey.to_world, DT_MS, 0.0)
    }
}

impl GridSource for SynthModel {
    fn dims(&self) -> [u64; 3] {
        self.dims
    }
    fn contiguous_axis(&self) -> usize {
        2
    }
    fn read_box(&self, lo: [u64; 3], size: [u64; 3], out: &mut [f32]) -> Result<()> {
        let (sx, sy, sz) = (size[0] as usize, size[1] as usize, size[2] as usize);
        let traces: Vec<Vec<f32>> = (0..sx * sy)
            .into_par_iter()
            .map_init(Vec::new, |scratch, t| {
                let mut tr = vec![0f32; sz];
                self.trace(
                    lo[0] + (t % sx) as u64,
                    lo[1] + (t / sx) as u64,
                    lo[2],
                    &mut tr,
                    scratch,
                );
                tr
            })
            .collect();
        for (t, tr) in traces.iter().enumerate() {
            for (k, &v) in tr.iter().enumerate() {
                out[k * sx * sy + t] = v;
            }
        }
        Ok(())
    }
}

/// What `synth` wrote.
#[derive(Debug)]
pub struct SynthOutput {
    /// The scene file.
    pub scene: PathBuf,
    /// The seismic store.
    pub volume: PathBuf,
    /// The three horizon stores.
    pub horizons: Vec<PathBuf>,
    /// The SEG-Y copy, if asked for.
    pub segy: Option<PathBuf>,
    /// Build report of the cube.
    pub volume_report: BuildReport,
}

/// Writes a synthetic survey into `dir`: `seismic.strata`, `horizon1..3.strata`, `scene.toml`,
/// and with `segy` also `seismic.sgy` and the horizons as `x y inline crossline z` text.
pub fn synth(
    dir: &Path,
    dims: [u64; 3],
    seed: u64,
    segy: bool,
    progress: &ProgressBar,
) -> Result<SynthOutput> {
    // The model's checks first: a size it refuses leaves no folder behind.
    let model = SynthModel::new(dims, seed)?;
    // So is a SEG-Y it could not write, before the stores are built.
    anyhow::ensure!(
        !segy || dims[2] <= u16::MAX as u64,
        "a SEG-Y trace holds at most {} samples (a 16-bit count), got {}",
        u16::MAX,
        dims[2]
    );
    std::fs::create_dir_all(dir)
        .with_context(|| format!("{}: cannot create folder", dir.display()))?;
    let units = Units {
        lateral: "m".into(),
        vertical: "ms".into(),
    };
    let volume = dir.join("seismic.strata");
    let mut vo = BuildOptions::volume("synthetic seismic", SampleType::F32);
    vo.transform = model.transform();
    vo.units = units.clone();
    vo.vertical_domain = Some(VerticalDomain::Time);
    vo.survey = Some(model.survey);
    vo.source = format!(
        "strata synth --seed {seed} --size {} {} {}",
        dims[0], dims[1], dims[2]
    );
    progress.set_message("seismic cube");
    let volume_report = build_store(&model, &volume, &vo, progress)?;

    let mut horizons = Vec::new();
    let grids = model.horizon_grids();
    for (h, grid) in grids.iter().enumerate() {
        let path = dir.join(format!("horizon{}.strata", h + 1));
        let mut ho = BuildOptions::horizon(&format!("synthetic horizon {}", h + 1));
        ho.transform = Affine3::from_lateral(&model.survey.to_world, 1.0, 0.0);
        ho.units = units.clone();
        ho.vertical_domain = Some(VerticalDomain::Time);
        ho.survey = Some(model.survey);
        ho.source = format!(
            "strata synth --seed {seed}, interface {}",
            model.horizon_layers[h]
        );
        let src = MemorySource {
            dims: [dims[0], dims[1], 1],
            data: grid.clone(),
        };
        progress.set_message(format!("horizon {}", h + 1));
        build_store(&src, &path, &ho, &ProgressBar::hidden())?;
        horizons.push(path);
    }

    let segy_path = if segy {
        let p = dir.join("seismic.sgy");
        progress.set_message("SEG-Y copy");
        write_segy(&model, &p)?;
        for (h, grid) in grids.iter().enumerate() {
            write_horizon_text(&model, grid, &dir.join(format!("horizon{}.txt", h + 1)))?;
        }
        Some(p)
    } else {
        None
    };

    let centre = model
        .survey
        .to_world
        .apply([dims[0] as f64 / 2.0, dims[1] as f64 / 2.0]);
    let diag = 25.0 * ((dims[0] * dims[0] + dims[1] * dims[1]) as f64).sqrt();
    let zc = dims[2] as f64 * DT_MS / 2.0;
    let scene = Scene {
        volumes: vec![VolumeLayer {
            store: "seismic.strata".into(),
            colormap: "seismic".into(),
            window: None,
            opacity: 0.6,
            opacity_points: None,
            slices: Vec::new(),
        }],
        horizons: (1..=3)
            .map(|h| HorizonLayer {
                store: format!("horizon{h}.strata").into(),
                color: [[0.95, 0.75, 0.2], [0.3, 0.8, 0.4], [0.3, 0.5, 0.95]][h - 1],
                opacity: 1.0,
                color_by: "constant".into(),
                colormap: "viridis".into(),
                volume: 0,
            })
            .collect(),
        camera: Some(Camera {
            eye: [
                centre[0] - 0.9 * diag,
                centre[1] - 0.6 * diag,
                zc - 0.8 * diag / Z_SCALE,
            ],
            target: [centre[0], centre[1], zc],
            up: [0.0, 0.0, -1.0],
            fov_deg: 35.0,
        }),
        render: RenderSettings {
            z_scale: Z_SCALE,
            ..RenderSettings::default()
        },
        synthetic: None,
        composite: Default::default(),
        cluster: Default::default(),
        wall: None,
    };
    let scene_path = dir.join("scene.toml");
    write_atomically(
        &scene_path,
        format!(
            "# Synthetic survey written by `coordinator synth` (seed {seed}).\n{}",
            scene.to_toml().map_err(|e| anyhow::anyhow!(e))?
        )
        .as_bytes(),
    )?;
    Ok(SynthOutput {
        scene: scene_path,
        volume,
        horizons,
        segy: segy_path,
        volume_report,
    })
}

/// Writes `bytes` under a temporary name and renames it into place.
///
/// The temporary file is created new (`O_EXCL`), never opened through whatever already has
/// its name: a symbolic link planted there (the name is predictable) would otherwise have
/// the bytes written wherever it points. A leftover of that name (a link, or a crashed
/// run's file) is removed first; removing a link does not touch its target.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    use std::io::Write;
    let tmp = crate::builder::temp_path_for(path);
    let _signals = crate::cleanup::register(&tmp);
    let create = || {
        std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&tmp)
    };
    let file = match create() {
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
            std::fs::remove_file(&tmp).and_then(|()| create())
        }
        other => other,
    };
    let result = file
        .and_then(|mut f| f.write_all(bytes))
        .with_context(|| {
            format!(
                "{}: cannot write (through {})",
                path.display(),
                tmp.display()
            )
        })
        .and_then(|()| {
            std::fs::rename(&tmp, path).with_context(|| {
                format!(
                    "{}: cannot replace it with {}",
                    path.display(),
                    tmp.display()
                )
            })
        });
    // Nothing half-written stays behind, whichever step failed.
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Writes the model as a big-endian IEEE-float SEG-Y file (inline-sorted), under a temporary name.
pub fn write_segy(model: &SynthModel, path: &Path) -> Result<()> {
    use crate::segy::{Endian, SegyWriter};
    let [nx, ny, nz] = model.dims;
    let tmp = crate::builder::temp_path_for(path);
    // Unlinked if a signal ends the process before the rename (a cube's worth of bytes).
    let _signals = crate::cleanup::register(&tmp);
    let result = (|| -> Result<()> {
        let text = format!(
            "Strata synthetic seismic survey, seed {}\nInlines {}..{}, crosslines {}..{}, {} samples at {} ms\nIEEE float, big-endian, inline 189 crossline 193",
            model.seed,
            model.survey.inline0,
            model.survey.inline0 + (nx - 1) as f64,
            model.survey.xline0,
            model.survey.xline0 + (ny - 1) as f64,
            nz,
            DT_MS
        );
        let mut w = SegyWriter::create(
            &tmp,
            &text,
            nz as u32,
            (DT_MS * 1000.0) as u32,
            0,
            5,
            Endian::Big,
        )?;
        // Inline-sorted, crossline fastest; traces are computed a row at a time in parallel.
        for i in 0..nx {
            let row: Vec<Vec<f32>> = (0..ny)
                .into_par_iter()
                .map_init(Vec::new, |s, j| {
                    let mut t = vec![0f32; nz as usize];
                    model.trace(i, j, 0, &mut t, s);
                    t
                })
                .collect();
            for (j, t) in row.iter().enumerate() {
                let [x, y] = model.survey.to_world.apply([i as f64, j as f64]);
                w.write_trace(
                    (model.survey.inline0 as i64 + i as i64) as i32,
                    (model.survey.xline0 as i64 + j as i64) as i32,
                    x,
                    y,
                    t,
                )?;
            }
        }
        w.finish()
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    std::fs::rename(&tmp, path)
        .with_context(|| format!("cannot rename {} to {}", tmp.display(), path.display()))
}

fn write_horizon_text(model: &SynthModel, grid: &[f32], path: &Path) -> Result<()> {
    use std::fmt::Write as _;
    let [nx, ny, _] = model.dims;
    let mut s = String::from(
        "# Strata synthetic horizon\n# X Y Inline Crossline Z(ms); holes are left out\n",
    );
    for i in 0..nx {
        for j in 0..ny {
            let z = grid[(j * nx + i) as usize];
            if z.is_nan() {
                continue;
            }
            let [x, y] = model.survey.to_world.apply([i as f64, j as f64]);
            let _ = writeln!(s, "{x:.2}\t{y:.2}\t{}\t{}\t{z:.3}", 1000 + i, 2000 + j);
        }
    }
    write_atomically(path, s.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A link planted under the predictable temporary name is not written through: the
    /// file it points to keeps its bytes, and the file asked for gets them.
    #[test]
    fn write_atomically_does_not_write_through_a_planted_link() {
        let dir = tempfile::tempdir().unwrap();
        let victim = dir.path().join("victim");
        std::fs::write(&victim, b"keep").unwrap();
        let out = dir.path().join("fingerprint");
        let tmp = crate::builder::temp_path_for(&out);
        std::os::unix::fs::symlink(&victim, &tmp).unwrap();
        write_atomically(&out, b"abc\n").unwrap();
        assert_eq!(std::fs::read(&victim).unwrap(), b"keep");
        assert_eq!(std::fs::read(&out).unwrap(), b"abc\n");
        assert!(
            std::fs::symlink_metadata(&tmp).is_err(),
            "the temporary name is gone"
        );
        // And over an existing file, as before.
        write_atomically(&out, b"xyz\n").unwrap();
        assert_eq!(std::fs::read(&out).unwrap(), b"xyz\n");
    }

    /// Sizes the outputs cannot take are refused before anything is written: a trace
    /// longer than SEG-Y counts (the stores had been built first, then left without their
    /// scene), and one deep enough to exhaust memory while the model's layers were made.
    #[test]
    fn sizes_the_outputs_cannot_take_are_refused_before_any_file() {
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("s");
        let e = synth(&dir, [8, 8, 70_000], 1, true, &ProgressBar::hidden()).unwrap_err();
        assert!(e.to_string().contains("16-bit"), "{e}");
        assert!(!dir.exists());
        let e = synth(
            &dir,
            [8, 8, 100_000_000_000],
            1,
            false,
            &ProgressBar::hidden(),
        )
        .unwrap_err();
        assert!(e.to_string().contains("2^20 samples per trace"), "{e}");
        assert!(!dir.exists());
    }

    /// Thin cubes (8 to 20 samples deep, the smallest allowed) have three distinct
    /// horizon layers whatever the seed; they panicked below 15 samples.
    #[test]
    fn thin_cubes_have_their_horizons_layers() {
        let mut out = Vec::new();
        for nz in 8..=20u64 {
            for seed in [0, 1, 7, u64::MAX] {
                let m = SynthModel::new([8, 8, nz], seed).unwrap();
                assert!(m.base.len() >= 4, "nz {nz}, seed {seed}");
                let [h1, h2, h3] = m.horizon_layers;
                assert!(1 <= h1 && h1 < h2 && h2 < h3, "nz {nz}: {h1} {h2} {h3}");
                assert!(
                    m.horizon_layers.iter().all(|&l| l < m.base.len()),
                    "nz {nz}, seed {seed}: layers {:?} of {}",
                    m.horizon_layers,
                    m.base.len()
                );
                for (i, j) in [(0.0, 0.0), (7.0, 7.0), (3.5, 4.5)] {
                    m.interfaces(i, j, &mut out);
                    assert_eq!(out.len(), m.base.len());
                }
            }
        }
    }
}
