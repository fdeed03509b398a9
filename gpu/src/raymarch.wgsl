// Volume ray march, one invocation per pixel.
//
// This is the WGSL twin of the CPU caster: every step below is written so that the CPU
// reference (gpu/tests/wgsl_matches_reference.rs) can repeat it operation for operation in
// f32. Builtins whose GPU precision is loose or implementation-defined (normalize, mix,
// clamp of NaN) are therefore spelled out, and the host rejects inputs (non-finite voxels,
// alpha outside [0, 1]) on which the two could legally diverge.

struct Params {
    // Rows of the affine world_to_index map: xyz = row of M, w = translation c.
    m0: vec4<f32>,
    m1: vec4<f32>,
    m2: vec4<f32>,
    // Ray of pixel (x, y) = dir00 + (x + 0.5) * du + (y + 0.5) * dv (camera-relative).
    dir00: vec4<f32>,      // w = step
    du: vec4<f32>,         // w = alpha_exponent
    dv: vec4<f32>,         // w = early_termination
    tf_range: vec4<f32>,   // x = lo, y = hi
    dims: vec4<u32>,       // xyz = volume dims, w = brick (0 = no skipping)
    cells: vec4<u32>,      // xyz = cell grid dims, w = transfer-function length
    image: vec4<u32>,      // x = width, y = height
};

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> vol: array<f32>;
@group(0) @binding(2) var<storage, read> tf: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> transparent: array<u32>;
@group(0) @binding(4) var<storage, read_write> out_px: array<vec4<f32>>;

// WGSL's mix is defined as a * (1 - t) + b * t; written out so both sides agree on the form.
fn lerp(a: f32, b: f32, t: f32) -> f32 {
    return a * (1.0 - t) + b * t;
}

fn lerp4(a: vec4<f32>, b: vec4<f32>, t: f32) -> vec4<f32> {
    return a * (1.0 - t) + b * t;
}

fn voxel(x: u32, y: u32, z: u32) -> f32 {
    return vol[(z * P.dims.y + y) * P.dims.x + x];
}

// Trilinear interpolation with voxel centres at integer coordinates. `qc` is already clamped
// to [0, dims - 1], so only the +1 neighbour can leave the volume and is clamped back.
fn sample_volume(qc: vec3<f32>) -> f32 {
    let f = floor(qc);
    let w = qc - f;
    let i0 = vec3<u32>(f);
    let i1 = min(i0 + vec3<u32>(1u), P.dims.xyz - vec3<u32>(1u));
    let c00 = lerp(voxel(i0.x, i0.y, i0.z), voxel(i1.x, i0.y, i0.z), w.x);
    let c10 = lerp(voxel(i0.x, i1.y, i0.z), voxel(i1.x, i1.y, i0.z), w.x);
    let c01 = lerp(voxel(i0.x, i0.y, i1.z), voxel(i1.x, i0.y, i1.z), w.x);
    let c11 = lerp(voxel(i0.x, i1.y, i1.z), voxel(i1.x, i1.y, i1.z), w.x);
    return lerp(lerp(c00, c10, w.y), lerp(c01, c11, w.y), w.z);
}

// Straight RGBA from the table, linear between entries.
//
// Alpha is fetched first and the colour only where alpha > 0: a zero-alpha sample contributes
// nothing, and buffer loads dominate the cost on lavapipe (Mesa 22 issues storage loads one
// lane and one component at a time), so this skips three quarters of the table traffic in
// empty space without changing any result.
fn classify(v: f32) -> vec4<f32> {
    let n = P.cells.w;
    if (n == 1u) {
        return tf[0];
    }
    let lo = P.tf_range.x;
    let hi = P.tf_range.y;
    let s = clamp((v - lo) / (hi - lo), 0.0, 1.0) * f32(n - 1u);
    let i = min(u32(floor(s)), n - 2u);
    let f = s - f32(i);
    let a = lerp(tf[i].a, tf[i + 1u].a, f);
    if (a <= 0.0) {
        return vec4<f32>(0.0);
    }
    return vec4<f32>(lerp4(tf[i], tf[i + 1u], f).rgb, a);
}

// [t_enter, t_exit] of the ray q(t) = c + t * md against the box [lo, hi] (slab method).
// Axes with a zero direction component constrain nothing if the origin lies inside the slab
// and empty the interval otherwise; dividing by them would produce inf/NaN, which WGSL lets
// implementations assume never occur.
fn slab(c: vec3<f32>, md: vec3<f32>, lo: vec3<f32>, hi: vec3<f32>) -> vec2<f32> {
    var t0 = -3.0e38;
    var t1 = 3.0e38;
    for (var a = 0; a < 3; a++) {
        if (md[a] == 0.0) {
            if (c[a] < lo[a] || c[a] > hi[a]) {
                return vec2<f32>(1.0, 0.0);
            }
        } else {
            let ta = (lo[a] - c[a]) / md[a];
            let tb = (hi[a] - c[a]) / md[a];
            t0 = max(t0, min(ta, tb));
            t1 = min(t1, max(ta, tb));
        }
    }
    return vec2<f32>(t0, t1);
}

// First lattice index k >= k_min with f32(k) * step >= t, exactly as evaluated in f32 (the
// division only gives a first guess that may be off by one either way).
fn first_lattice_at_or_after(t: f32, step: f32, k_min: u32) -> u32 {
    var k = max(u32(max(ceil(t / step), 0.0)), k_min);
    while (k > k_min && f32(k - 1u) * step >= t) {
        k -= 1u;
    }
    while (f32(k) * step < t) {
        k += 1u;
    }
    return k;
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let width = P.image.x;
    if (gid.x >= width || gid.y >= P.image.y) {
        return;
    }
    let step = P.dir00.w;
    let alpha_exponent = P.du.w;
    let early_termination = P.dv.w;
    let brick = P.dims.w;

    // 1. Ray direction. normalize() may use an approximate inverse square root; an explicit
    //    sqrt and divide keeps the CPU reference within an ulp.
    let r = P.dir00.xyz + (f32(gid.x) + 0.5) * P.du.xyz + (f32(gid.y) + 0.5) * P.dv.xyz;
    let d = r / sqrt(dot(r, r));

    // 2. Index space: q(t) = c + t * md.
    let c = vec3<f32>(P.m0.w, P.m1.w, P.m2.w);
    let md = vec3<f32>(dot(P.m0.xyz, d), dot(P.m1.xyz, d), dot(P.m2.xyz, d));
    let dims_f = vec3<f32>(P.dims.xyz);
    let box_lo = vec3<f32>(-0.5);
    let box_hi = dims_f - vec3<f32>(0.5);
    let span = slab(c, md, box_lo, box_hi);
    let t0 = max(span.x, 0.0);
    let t1 = span.y;

    var acc = vec4<f32>(0.0);
    if (t0 < t1) {
        // 3. Global sample lattice t_k = k * step, so that neighbouring bricks and the CPU
        //    caster sample at exactly the same distances.
        var k = first_lattice_at_or_after(t0, step, 0u);
        let q_max = dims_f - vec3<f32>(1.0);
        loop {
            let t = f32(k) * step;
            if (t >= t1) {
                break;
            }
            let q = c + t * md;
            let qc = clamp(q, vec3<f32>(0.0), q_max);

            // 4. Empty-space skipping: jump over a cell whose every sample is transparent.
            if (brick > 0u) {
                let cell = min(vec3<u32>(floor(qc / f32(brick))), P.cells.xyz - vec3<u32>(1u));
                let flag = transparent[(cell.z * P.cells.y + cell.y) * P.cells.x + cell.x];
                if (flag != 0u) {
                    let cell_lo = max(vec3<f32>(cell * brick) - vec3<f32>(0.5), box_lo);
                    let cell_hi = min(vec3<f32>((cell + vec3<u32>(1u)) * brick) - vec3<f32>(0.5), box_hi);
                    let t_exit = slab(c, md, cell_lo, cell_hi).y;
                    // k + 1 at least, so rounding at a cell face can never stall the ray.
                    k = first_lattice_at_or_after(t_exit, step, k + 1u);
                    continue;
                }
            }

            // 5. Classify, correct opacity for the step length, composite front to back.
            var rgba = classify(sample_volume(qc));
            if (rgba.a > 0.0) {
                if (alpha_exponent != 1.0) {
                    if (rgba.a >= 1.0) {
                        // pow(0, e) would go through log2(0) = -inf.
                        rgba.a = 1.0;
                    } else {
                        rgba.a = 1.0 - pow(1.0 - rgba.a, alpha_exponent);
                    }
                }
                let w = (1.0 - acc.a) * rgba.a;
                acc = vec4<f32>(acc.rgb + w * rgba.rgb, acc.a + w);
                if (acc.a >= early_termination) {
                    break;
                }
            }
            k += 1u;
        }
    }
    out_px[gid.y * width + gid.x] = acc;
}
