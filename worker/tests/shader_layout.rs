//! The caster's WGSL, checked without an adapter: naga parses and validates it, and its
//! structs have exactly the sizes and member offsets of the `strata_common::gpu` records the
//! host uploads.

use naga::valid::{Capabilities, ValidationFlags, Validator};
use strata_common::gpu::{self, FrameParams, HorizonParams, VolumeParams};
use strata_worker::gpu::SHADER;

fn module() -> naga::Module {
    naga::front::wgsl::parse_str(SHADER).unwrap_or_else(|e| panic!("{}", e.emit_to_string(SHADER)))
}

#[test]
fn wgsl_parses_and_validates() {
    let m = module();
    Validator::new(ValidationFlags::all(), Capabilities::all())
        .validate(&m)
        .unwrap_or_else(|e| panic!("{}", e.emit_to_string(SHADER)));
    let entries: Vec<&str> = m.entry_points.iter().map(|e| e.name.as_str()).collect();
    assert_eq!(entries, ["cast_rays", "compact"]);
}

fn struct_layout(m: &naga::Module, name: &str) -> (u32, Vec<(String, u32)>) {
    let (_, ty) = m
        .types
        .iter()
        .find(|(_, t)| t.name.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("no struct {name} in the WGSL"));
    match &ty.inner {
        naga::TypeInner::Struct { members, span } => (
            *span,
            members
                .iter()
                .map(|mb| (mb.name.clone().unwrap_or_default(), mb.offset))
                .collect(),
        ),
        _ => panic!("{name} is not a struct"),
    }
}

fn check(name: &str, size: usize, rust: Vec<(&'static str, usize)>) {
    let m = module();
    let (span, members) = struct_layout(&m, name);
    assert_eq!(
        span as usize, size,
        "size of {name}: WGSL {span}, Rust {size}"
    );
    for (field, off) in rust {
        let (_, o) = members
            .iter()
            .find(|(n, _)| n == field)
            .unwrap_or_else(|| panic!("{name}.{field} is missing in the WGSL"));
        assert_eq!(
            *o as usize, off,
            "{name}.{field}: WGSL offset {o}, Rust {off}"
        );
    }
}

#[test]
fn frame_struct_matches_the_host_record() {
    check(
        "Frame",
        std::mem::size_of::<FrameParams>(),
        gpu::frame_params_offsets(),
    );
}

#[test]
fn volume_struct_matches_the_host_record() {
    check(
        "Volume",
        std::mem::size_of::<VolumeParams>(),
        gpu::volume_params_offsets(),
    );
}

#[test]
fn horizon_struct_matches_the_host_record() {
    check(
        "Horizon",
        std::mem::size_of::<HorizonParams>(),
        gpu::horizon_params_offsets(),
    );
}

#[test]
fn shader_constants_match_the_host() {
    // The constants the host sizes buffers with.
    for (name, want) in [
        ("TF_SIZE", gpu::TF_SIZE as u64),
        ("MAX_VOLS", strata_worker::gpu::MAX_VOLUMES as u64),
        ("NOT_RESIDENT", gpu::NOT_RESIDENT as u64),
        ("SLOT_MASK", gpu::SLOT_MASK as u64),
        ("LEVEL_MASK", gpu::LEVEL_MASK as u64),
        ("ENTRY_FRAGMENTED", gpu::ENTRY_FRAGMENTED as u64),
        ("MAX_HORS", gpu::MAX_HORIZONS as u64),
        ("HORIZON_DEPTH_MAP", gpu::HORIZON_DEPTH_MAP as u64),
        ("HORIZON_LIGHTING", gpu::HORIZON_LIGHTING as u64),
    ] {
        let line = SHADER
            .lines()
            .find(|l| l.starts_with(&format!("const {name}:")))
            .unwrap_or_else(|| panic!("const {name} missing"));
        let v = line.split('=').nth(1).unwrap().trim().trim_end_matches(';');
        let v = v.trim_end_matches('u');
        let got = if let Some(h) = v.strip_prefix("0x") {
            u64::from_str_radix(h, 16).unwrap()
        } else {
            v.parse().unwrap()
        };
        assert_eq!(got, want, "{name}");
    }
    let levels = SHADER.contains(&format!("level_t: array<f32, {}>", gpu::MAX_LEVELS));
    assert!(levels, "Volume.level_t holds MAX_LEVELS entries");
}
