// Strata's volume ray caster on the GPU: the CPU caster's semantics (worker/src/raycast.rs,
// worker/src/volume.rs) over the shared tables of strata_common::gpu.
//
// One invocation per pixel of the region's screen rectangle. A ray is clipped to the
// region's half-open t interval and marched on the global sample lattice t = k·dt, with dt
// doubling by distance band, so every region takes exactly the samples the whole ray would.
// Each brick the ray enters is looked up at the level its footprint calls for (the LOD
// distances in level_t) through the page table, which names the page's own slot or that of
// its nearest resident ancestor; the entered page is counted in the feedback buffer (one
// atomic counter per virtual page) unless it is transparent under the transfer function.
// `compact` then turns the counters into a short list for the host.
//
// Horizons (worker/src/horizon.rs) are intersected first: each ray descends the horizon's
// min-max tile tree front to back with an explicit stack, down to the tile level its
// footprint calls for, and walks that tile's cells (of the finest resident level) with a 2D
// DDA, solving the ray against each cell's bilinear patch exactly. The crossings, sorted, cut
// the volume march into segments; each surface is composited when the march reaches it.
//
// Effects are pipeline-overridable constants, so a scene without them runs no code for them
// (strata_common::effects): SHADING (gradient shading), MULTI (several volumes mixed per
// sample), HORIZONS, LIGHTING (of horizons), SLICES. The general pipeline has them all on
// and decides per frame (F.flags) and per horizon (flags).

const TF_SIZE: u32 = 1024u;
const MAX_VOLS: u32 = 4u;
const NOT_RESIDENT: u32 = 0xffffffffu;
const SLOT_MASK: u32 = 0xffffffu;
const LEVEL_MASK: u32 = 0x7fu;
const ENTRY_FRAGMENTED: u32 = 0x80000000u;
const BIG: f32 = 3.0e38; // stands in for +infinity (WGSL has no infinity literal)
const MAX_HORS: u32 = 16u;
const HORIZON_DEPTH_MAP: u32 = 1u;
const HORIZON_LIGHTING: u32 = 2u;
const FRAME_SHADING: u32 = 1u;
const NO_VOLUME: u32 = 0xffffffffu;
// Surface crossings a ray keeps (the nearest ones; the CPU keeps 32 per horizon).
const MAX_HITS: u32 = 32u;
// Tile-tree traversal stack: at most 3 siblings wait per level below the root, plus one.
const STACK: u32 = 52u;

override SHADING: bool = false;
override MULTI: bool = false;
override HORIZONS: bool = false;
override LIGHTING: bool = false;
// Bits per element of the volume pool (strata_common::gpu::PoolFormat): 8, 16 or 32.
override POOL_BITS: u32 = 32u;
// Volume samples through the texture unit's filter (render.gpu_filter = "hardware") from the
// 3D-texture pool, instead of the shader's trilinear from the storage-buffer pool.
override HW_FILTER: bool = false;
// Some volume has slices: crossings are collected even without horizons.
override SLICES: bool = false;
// render.preintegrated: volumes flagged VOLUME_PREINTEGRATED march segment by segment
// through their pre-integrated tables (raycast.rs `march_typed` with PRE).
override PRE: bool = false;
const VOLUME_PREINTEGRATED: u32 = 8u;
const PREINT_SIZE: u32 = 256u;
const VOLUME_SIGNED: u32 = 1u;
const VOLUME_NO_DATA: u32 = 2u;
const VOLUME_INVISIBLE: u32 = 4u;

struct Frame {
    dir00: vec3<f32>,
    width: u32,
    du: vec3<f32>,
    height: u32,
    dv: vec3<f32>,
    rect_x: u32,
    region_lo: vec3<f32>,
    rect_y: u32,
    region_hi: vec3<f32>,
    rect_w: u32,
    band_start: array<vec4<f32>, 2>,
    band_dt: array<vec4<f32>, 2>,
    rect_h: u32,
    n_bands: u32,
    n_vols: u32,
    ert: f32,
    flags: u32,
    fb_entries: u32,
    n_hors: u32,
    // Cross-worker occlusion: block side of `occl` (0: no per-ray limits).
    occl_block: u32,
    // A wall's tiles: image pixel -> plane pixel (see `plane_pixel`).
    tile_cols: u32,
    tile_h: u32,
    pitch_x: u32,
    pitch_y: u32,
}

struct Volume {
    m0: vec3<f32>,
    core: f32,
    m1: vec3<f32>,
    border: f32,
    m2: vec3<f32>,
    page: u32,
    c: vec3<f32>,
    n_levels: u32,
    hi: vec3<f32>,
    table_base: u32,
    level_base: u32,
    tf_base: u32,
    tf_scale: f32,
    tf_offset: f32,
    tf_last: f32,
    pool_base: u32,
    flags: u32,
    no_data: i32,
    level_t: array<f32, 16>,
    n_slices: u32,
    straight_base: u32,
    // Slice s is tf[slice_base + s] = (axis, level-0 index, opacity, 0).
    slice_base: u32,
    // With VOLUME_PREINTEGRATED: tf[pre_base] = (scale, offset, last, 0) of the value ->
    // table position map, then per band the whole-step and the half-step table.
    pre_base: u32,
}

struct Horizon {
    m0: vec3<f32>,
    core: u32,
    m1: vec3<f32>,
    border: u32,
    m2: vec3<f32>,
    page: u32,
    c: vec3<f32>,
    n_levels: u32,
    color: vec3<f32>,
    opacity: f32,
    dims: vec2<u32>,
    table_base: u32,
    level_base: u32,
    bounds_base: u32,
    map_base: u32,
    map_len: u32,
    flags: u32,
    depth_lo: f32,
    depth_hi: f32,
    pool_base: u32,
    // color_by = "volume": the volume whose colour multiplies each hit (NO_VOLUME: none).
    attr_vol: u32,
    level_t: array<f32, 16>,
}

struct Cursor {
    level: u32,
    t_exit: f32,
    transparent: bool,
    base: u32,
    s: f32,
    o: vec3<f32>,
    // First texel of the slot in the texture pool (HW_FILTER).
    tex_o: vec3<f32>,
    // Pre-integration (raycast.rs `Cursor`): the ray's previous sample of this volume (valid
    // with has_prev), the one before it, whether the half step before `prev` is still to be
    // composited, `prev`'s light, and where the ray leaves the volume.
    has_prev: bool,
    prev: f32,
    before: f32,
    // The sampling band `prev` was taken in.
    prev_band: u32,
    lead: bool,
    // The span (or the next) begins after skipped empty space: its lead is a whole step.
    gap: bool,
    // The value's change along the ray over one step at a span's first sample (central
    // differences): a one-sample span's ends are extrapolated by it.
    slope: f32,
    prev_light: vec2<f32>,
    span_end: f32,
    // Where the ray enters and leaves the volume itself (not its part of the region), and
    // whether it has sampled it yet (raycast.rs: the lattice points either side of a region
    // that another region may skip as hidden).
    vol_start: f32,
    vol_end: f32,
    entered: bool,
}

@group(0) @binding(0) var<uniform> F: Frame;
@group(0) @binding(1) var<storage, read> vols: array<Volume>;
// x = first entry of the level in its data set's table, yzw = bricks per axis.
@group(0) @binding(2) var<storage, read> levels: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> table: array<u32>;
// One bit per page-table entry: nothing in the page is visible under the transfer function.
@group(0) @binding(4) var<storage, read> transparent: array<u32>;
@group(0) @binding(5) var<storage, read> tf: array<vec4<f32>>;
// The volume pool: slots of page³ elements of POOL_BITS bits (x fastest), packed in words.
@group(0) @binding(6) var<storage, read> pool: array<u32>;
@group(0) @binding(7) var<storage, read_write> feedback: array<atomic<u32>>;
@group(0) @binding(8) var<storage, read_write> out_px: array<vec4<f32>>;
// samples lo/hi, skipped lo/hi, terminated, rays, hits.
@group(0) @binding(9) var<storage, read_write> stats: array<atomic<u32>, 8>;
@group(0) @binding(12) var<storage, read> hors: array<Horizon>;
// [min, max] height per tile of every horizon, page-table order; min > max: all holes.
@group(0) @binding(13) var<storage, read> hbounds: array<vec2<f32>>;
// The horizon pool: slots of page² heights (i fastest), NaN = hole.
@group(0) @binding(14) var<storage, read> hpool: array<f32>;
// The volume pool as a 3D texture (HW_FILTER): slot s is the page³ block at grid position
// (s mod gx, s / gx mod gy, s / (gx·gy)); unsigned-normalized texels hold signed values
// biased by 2^(POOL_BITS−1), f32 texels the values themselves.
@group(0) @binding(15) var pool_tex: texture_3d<f32>;
@group(0) @binding(16) var pool_samp: sampler;
// Cross-worker occlusion (occlusion.rs `RayLimits`): per screen block of `F.occl_block`
// pixels, the termination threshold of its rays, or < 0 where they are not cast.
@group(0) @binding(17) var<storage, read> occl: array<f32>;

// A ray's surface crossings, nearest first.
var<private> n_hits: u32;
// Whether the list filled since the last search began (crossings may lie beyond it).
var<private> hits_full: bool;
// The last crossing the current horizon's search kept (-BIG before the first): a crossing
// on the edge between two cells is kept by the first of them up to EDGE_REL past the edge
// and dropped by the next (horizon.rs `EDGE_REL`).
var<private> h_last: f32;
const EDGE_REL: f32 = 9.5367431640625e-7; // 2^-20
var<private> hit_t: array<f32, MAX_HITS>;
var<private> hit_c: array<vec4<f32>, MAX_HITS>;

var<workgroup> wg_samples: atomic<u32>;
var<workgroup> wg_skipped: atomic<u32>;
var<workgroup> wg_terminated: atomic<u32>;
var<workgroup> wg_rays: atomic<u32>;
var<workgroup> wg_hits: atomic<u32>;

fn band_start(b: u32) -> f32 {
    return F.band_start[b >> 2u][b & 3u];
}

fn band_dt(b: u32) -> f32 {
    return F.band_dt[b >> 2u][b & 3u];
}

fn band_end(b: u32) -> f32 {
    if (b + 1u < F.n_bands) {
        return band_start(b + 1u);
    }
    return BIG;
}

fn is_nan(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7fffffffu) > 0x7f800000u;
}

fn is_finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

// First lattice index k with f32(k)·dt >= t (the loops make it exact whatever the division).
fn first_k(t: f32, dt: f32) -> i32 {
    var k = i32(ceil(t / dt));
    loop {
        if (f32(k - 1) * dt >= t) { k = k - 1; } else { break; }
    }
    loop {
        if (f32(k) * dt < t) { k = k + 1; } else { break; }
    }
    return k;
}

// Half-open [t0, t1) of the ray (origin 0) inside the box [lo, hi).
fn clip_region(lo: vec3<f32>, hi: vec3<f32>, d: vec3<f32>) -> vec2<f32> {
    var t0 = 0.0;
    var t1 = BIG;
    for (var a = 0u; a < 3u; a = a + 1u) {
        if (d[a] == 0.0) {
            if (!(lo[a] <= 0.0 && 0.0 < hi[a])) {
                return vec2<f32>(0.0, 0.0);
            }
        } else {
            let ta = lo[a] / d[a];
            let tb = hi[a] / d[a];
            t0 = max(t0, min(ta, tb));
            t1 = min(t1, max(ta, tb));
        }
    }
    return vec2<f32>(t0, t1);
}

// M·v for the 3×3 matrix with rows m0, m1, m2 (the CPU's operation order).
fn mul_rows(m0: vec3<f32>, m1: vec3<f32>, m2: vec3<f32>, v: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(
        m0.x * v.x + m0.y * v.y + m0.z * v.z,
        m1.x * v.x + m1.y * v.y + m1.z * v.z,
        m2.x * v.x + m2.y * v.y + m2.z * v.z,
    );
}

// Mᵀ·v: an index-space gradient or normal to camera space.
fn mul_cols(m0: vec3<f32>, m1: vec3<f32>, m2: vec3<f32>, v: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(
        m0.x * v.x + m1.x * v.y + m2.x * v.z,
        m0.y * v.x + m1.y * v.y + m2.y * v.z,
        m0.z * v.x + m1.z * v.y + m2.z * v.z,
    );
}

fn index_dir(vi: u32, d: vec3<f32>) -> vec3<f32> {
    return mul_rows(vols[vi].m0, vols[vi].m1, vols[vi].m2, d);
}

// [t0, t1) of the ray inside the volume's index box [-0.5, hi).
fn interval(vi: u32, md: vec3<f32>) -> vec2<f32> {
    let c = vols[vi].c;
    let hi = vols[vi].hi;
    var t0 = -BIG;
    var t1 = BIG;
    for (var a = 0u; a < 3u; a = a + 1u) {
        if (md[a] == 0.0) {
            if (!(-0.5 <= c[a] && c[a] < hi[a])) {
                return vec2<f32>(0.0, 0.0);
            }
        } else {
            let ta = (-0.5 - c[a]) / md[a];
            let tb = (hi[a] - c[a]) / md[a];
            t0 = max(t0, min(ta, tb));
            t1 = min(t1, max(ta, tb));
        }
    }
    return vec2<f32>(t0, t1);
}

fn level_t(vi: u32, l: u32) -> f32 {
    return vols[vi].level_t[l];
}

// Moves the cursor to the brick holding the sample at t (index position q).
fn locate(vi: u32, cur: ptr<function, Cursor>, t: f32, q: vec3<f32>, md: vec3<f32>) {
    locate_page(vi, cur, t, q, md, true);
}

// `locate`; with `skip_transparent` false, pages invisible under the transfer function are
// located (and requested) too: a slice shows every value (volume.rs `locate_page`).
// Whether the sample at t (index position q) lies in a brick the transfer function hides, at
// the level its distance calls for, from the transparency bits alone (volume.rs `hidden_at`).
fn hidden_at(vi: u32, t: f32, q: vec3<f32>) -> bool {
    let nl = vols[vi].n_levels;
    let core = vols[vi].core;
    var level = 0u;
    loop {
        if (level + 1u < nl && t >= level_t(vi, level + 1u)) { level = level + 1u; } else { break; }
    }
    let scale = ldexp(1.0, -i32(level));
    let li = levels[vols[vi].level_base + level];
    let bricks = li.yzw;
    var b = vec3<u32>(0u);
    for (var a = 0u; a < 3u; a = a + 1u) {
        let f = floor((q[a] + 0.5) * scale / core);
        b[a] = min(u32(max(f, 0.0)), bricks[a] - 1u);
    }
    let g = vols[vi].table_base + li.x + (b.z * bricks.y + b.y) * bricks.x + b.x;
    return ((transparent[g >> 5u] >> (g & 31u)) & 1u) != 0u;
}

fn locate_page(vi: u32, cur: ptr<function, Cursor>, t: f32, q: vec3<f32>, md: vec3<f32>, skip_transparent: bool) {
    let nl = vols[vi].n_levels;
    let core = vols[vi].core;
    let c = vols[vi].c;
    var level = (*cur).level;
    loop {
        if (level + 1u < nl && t >= level_t(vi, level + 1u)) { level = level + 1u; } else { break; }
    }
    (*cur).level = level;
    let scale = ldexp(1.0, -i32(level));
    let li = levels[vols[vi].level_base + level];
    let bricks = li.yzw;
    var t_exit = BIG;
    if (level + 1u < nl) {
        t_exit = level_t(vi, level + 1u);
    }
    let span = core / scale;
    var b = vec3<u32>(0u);
    for (var a = 0u; a < 3u; a = a + 1u) {
        let f = floor((q[a] + 0.5) * scale / core);
        let bi = min(u32(max(f, 0.0)), bricks[a] - 1u);
        b[a] = bi;
        if (md[a] != 0.0) {
            var bound = f32(bi) * span - 0.5;
            if (md[a] > 0.0) {
                bound = f32(bi + 1u) * span - 0.5;
            }
            t_exit = min(t_exit, (bound - c[a]) / md[a]);
        }
    }
    (*cur).t_exit = t_exit;
    let g = vols[vi].table_base + li.x + (b.z * bricks.y + b.y) * bricks.x + b.x;
    if (skip_transparent && ((transparent[g >> 5u] >> (g & 31u)) & 1u) != 0u) {
        (*cur).transparent = true;
        return;
    }
    atomicAdd(&feedback[g], 1u);
    let e = table[g];
    if (e == NOT_RESIDENT) {
        (*cur).transparent = true;
        return;
    }
    (*cur).transparent = false;
    let r = e >> 24u;
    let slot = e & SLOT_MASK;
    let sr = ldexp(1.0, -i32(r));
    let k = r - level;
    let p = vols[vi].page;
    (*cur).base = vols[vi].pool_base + slot * slot_elems(p);
    if (HW_FILTER) {
        let grid = textureDimensions(pool_tex) / p;
        let g = vec3<u32>(slot % grid.x, slot / grid.x % grid.y, slot / (grid.x * grid.y));
        (*cur).tex_o = vec3<f32>(g * p);
    }
    (*cur).s = sr;
    let border = vols[vi].border;
    for (var a = 0u; a < 3u; a = a + 1u) {
        let br = f32(b[a] >> k);
        (*cur).o[a] = 0.5 * sr - 0.5 - br * core + border;
    }
}

// Elements of a slot: page³ rounded up to whole words (strata_common::gpu::PoolFormat).
fn slot_elems(p: u32) -> u32 {
    let per_word = 32u / POOL_BITS;
    return (p * p * p + per_word - 1u) / per_word * per_word;
}

// Pool element i as the f32 of the host's decoded page (PoolFormat::decode).
fn fetch(i: u32, flags: u32, nd: i32) -> f32 {
    if (POOL_BITS == 32u) {
        return bitcast<f32>(pool[i]);
    }
    // Element i of POOL_BITS bits inside its word, sign- or zero-extended.
    let per_word = 32u / POOL_BITS;
    let w = pool[i / per_word];
    let off = (i % per_word) * POOL_BITS;
    var raw: i32;
    if ((flags & VOLUME_SIGNED) != 0u) {
        raw = extractBits(bitcast<i32>(w), off, POOL_BITS);
    } else {
        raw = i32(extractBits(w, off, POOL_BITS));
    }
    if ((flags & VOLUME_NO_DATA) != 0u && raw == nd) {
        return nan_f32();
    }
    return f32(raw);
}

// Trilinear blend of a cell's corner values v[x + 2y + 4z] at fractions f (the CPU's
// operation order).
fn blend8(v: array<f32, 8>, f: vec3<f32>) -> f32 {
    let c00 = v[0] + f.x * (v[1] - v[0]);
    let c10 = v[2] + f.x * (v[3] - v[2]);
    let c01 = v[4] + f.x * (v[5] - v[4]);
    let c11 = v[6] + f.x * (v[7] - v[6]);
    let c0 = c00 + f.y * (c10 - c00);
    let c1 = c01 + f.y * (c11 - c01);
    return c0 + f.z * (c1 - c0);
}

// Trilinear interpolation in a p³ page of the buffer pool at local coordinates l within
// [0, p − 1).
fn trilinear(vi: u32, base: u32, p: u32, l: vec3<f32>) -> f32 {
    let fl = vols[vi].flags;
    let nd = vols[vi].no_data;
    let c = vec3<u32>(l);
    let i = base + (c.z * p + c.y) * p + c.x;
    let sy = p;
    let sz = p * p;
    let v = array<f32, 8>(
        fetch(i, fl, nd),
        fetch(i + 1u, fl, nd),
        fetch(i + sy, fl, nd),
        fetch(i + sy + 1u, fl, nd),
        fetch(i + sz, fl, nd),
        fetch(i + sz + 1u, fl, nd),
        fetch(i + sz + sy, fl, nd),
        fetch(i + sz + sy + 1u, fl, nd),
    );
    return blend8(v, l - vec3<f32>(c));
}

// A texel (normalized or f32) as the value the host's decoded page holds.
fn texel_value(vi: u32, t: f32) -> f32 {
    if (POOL_BITS == 32u) {
        return t;
    }
    // exp2 of a small integer is exact (and a shift by 32 would not compile for f32 pools).
    var bias = 0.0;
    if ((vols[vi].flags & VOLUME_SIGNED) != 0u) {
        bias = exp2(f32(POOL_BITS - 1u));
    }
    return t * (exp2(f32(POOL_BITS)) - 1.0) - bias;
}

// Trilinear in the shader from the texture pool's texels, the no-data sentinel becoming NaN:
// the texture unit would blend the sentinel into its neighbours.
fn tex_trilinear(vi: u32, cur: ptr<function, Cursor>, l: vec3<f32>) -> f32 {
    let c = vec3<u32>(l);
    let o = vec3<i32>((*cur).tex_o) + vec3<i32>(c);
    let nd = vols[vi].no_data;
    var v: array<f32, 8>;
    for (var k = 0u; k < 8u; k = k + 1u) {
        let d = vec3<i32>(i32(k & 1u), i32((k >> 1u) & 1u), i32(k >> 2u));
        let raw = round(texel_value(vi, textureLoad(pool_tex, o + d, 0).x));
        v[k] = select(raw, nan_f32(), i32(raw) == nd);
    }
    return blend8(v, l - vec3<f32>(c));
}

// The volume's value at page-local position l: the shader's trilinear, or the texture
// unit's filter (HW_FILTER; many GPUs use 8-bit weights there).
fn filtered(vi: u32, cur: ptr<function, Cursor>, l: vec3<f32>) -> f32 {
    if (!HW_FILTER) {
        return trilinear(vi, (*cur).base, vols[vi].page, l);
    }
    if ((vols[vi].flags & VOLUME_NO_DATA) != 0u) {
        return tex_trilinear(vi, cur, l);
    }
    let dims = vec3<f32>(textureDimensions(pool_tex));
    let uvw = ((*cur).tex_o + l + vec3<f32>(0.5)) / dims;
    return texel_value(vi, textureSampleLevel(pool_tex, pool_samp, uvw, 0.0).x);
}

fn local(vi: u32, cur: ptr<function, Cursor>, q: vec3<f32>, dx: vec3<f32>) -> vec3<f32> {
    let maxc = f32(vols[vi].page - 1u) - 1e-3;
    return clamp(q * (*cur).s + (*cur).o + dx, vec3<f32>(0.0), vec3<f32>(maxc));
}

fn sample_at(vi: u32, cur: ptr<function, Cursor>, q: vec3<f32>) -> f32 {
    return filtered(vi, cur, local(vi, cur, q, vec3<f32>(0.0)));
}

fn tap(vi: u32, cur: ptr<function, Cursor>, q: vec3<f32>, dx: vec3<f32>) -> f32 {
    return filtered(vi, cur, local(vi, cur, q, dx));
}

// Premultiplied, step-corrected RGBA of value s in band b.
fn classify(vi: u32, band: u32, s: f32) -> vec4<f32> {
    let v = &vols[vi];
    let x = clamp(s * (*v).tf_scale + (*v).tf_offset, 0.0, (*v).tf_last);
    let i = min(u32(x), TF_SIZE - 2u); // tables hold TF_SIZE entries (checked on upload)
    let f = x - f32(i);
    let o = (*v).tf_base + band * TF_SIZE + i;
    let a = tf[o];
    let b = tf[o + 1u];
    return a + f * (b - a);
}

// Headlight Blinn-Phong factors from the index-space gradient (central differences):
// (ambient + diffuse, specular per unit of opacity), or (1, 0) where the gradient vanishes.
fn light(vi: u32, cur: ptr<function, Cursor>, q: vec3<f32>, d: vec3<f32>) -> vec2<f32> {
    let g = vec3<f32>(
        tap(vi, cur, q, vec3<f32>(1.0, 0.0, 0.0)) - tap(vi, cur, q, vec3<f32>(-1.0, 0.0, 0.0)),
        tap(vi, cur, q, vec3<f32>(0.0, 1.0, 0.0)) - tap(vi, cur, q, vec3<f32>(0.0, -1.0, 0.0)),
        tap(vi, cur, q, vec3<f32>(0.0, 0.0, 1.0)) - tap(vi, cur, q, vec3<f32>(0.0, 0.0, -1.0)),
    );
    let n = mul_cols(vols[vi].m0, vols[vi].m1, vols[vi].m2, g);
    let len = sqrt(n.x * n.x + n.y * n.y + n.z * n.z);
    if (!(len > 1e-12) || !is_finite(len)) {
        return vec2<f32>(1.0, 0.0);
    }
    let cosv = abs((n.x * d.x + n.y * d.y + n.z * d.z) / len);
    let k = 0.3 + 0.6 * cosv;
    let c2 = cosv * cosv;
    let c4 = c2 * c2;
    let c8 = c4 * c4;
    let c16 = c8 * c8;
    return vec2<f32>(k, 0.25 * (c16 * c8));
}

// A premultiplied colour lit with light()'s factors.
fn apply_light(rgba: vec4<f32>, l: vec2<f32>) -> vec4<f32> {
    return vec4<f32>(rgba.xyz * l.x + vec3<f32>(l.y * rgba.w), rgba.w);
}

fn shade(vi: u32, cur: ptr<function, Cursor>, q: vec3<f32>, d: vec3<f32>, rgba: vec4<f32>) -> vec4<f32> {
    return apply_light(rgba, light(vi, cur, q, d));
}

// The pre-integrated table between entries at positions (pf, pb), clamped into it.
fn pre_bilinear(o: u32, last: f32, pf0: f32, pb0: f32) -> vec4<f32> {
    let n = PREINT_SIZE;
    let pf = clamp(pf0, 0.0, last);
    let pb = clamp(pb0, 0.0, last);
    let i = min(u32(pf), n - 2u);
    let j = min(u32(pb), n - 2u);
    let u = pf - f32(i);
    let v = pb - f32(j);
    let a = tf[o + i * n + j];
    let b = tf[o + i * n + j + 1u];
    let c = tf[o + (i + 1u) * n + j];
    let e = tf[o + (i + 1u) * n + j + 1u];
    let top = a + v * (b - a);
    let bottom = c + v * (e - c);
    return top + u * (bottom - top);
}

// A premultiplied segment over a share w of its length (tf.rs `scaled`).
fn pre_scaled(rgba: vec4<f32>, w: f32) -> vec4<f32> {
    let a = rgba.w;
    if (a >= 1.0 || w >= 1.0) {
        return rgba;
    }
    if (a <= 0.0 || w <= 0.0) {
        return vec4<f32>(0.0);
    }
    let aw = 1.0 - pow(1.0 - a, w);
    let k = aw / a;
    return vec4<f32>(rgba.xyz * k, aw);
}

// Premultiplied RGBA of a segment from value `front` to value `back` in band b (bilinear
// between entries; tf.rs `PreintTable::lookup_in`); `half`: a segment half a step long. A
// segment that leaves the window is cut at its edges, each piece scaled to its share.
fn pre_lookup(vi: u32, band: u32, half: bool, front: f32, back: f32) -> vec4<f32> {
    let base = vols[vi].pre_base;
    let map = tf[base];
    let n = PREINT_SIZE;
    var o = base + 1u + band * 2u * n * n;
    if (half) { o = o + n * n; }
    let last = map.z;
    let pf = front * map.x + map.y;
    let pb = back * map.x + map.y;
    let inside = pf >= 0.0 && pf <= last && pb >= 0.0 && pb <= last;
    if (inside || !is_finite(pf - pb)) {
        return pre_bilinear(o, last, pf, pb);
    }
    var cuts = array<f32, 4>(pf, 0.0, 0.0, pb);
    var m = 1u;
    let lo = min(pf, pb);
    let hi = max(pf, pb);
    var edges = vec2<f32>(0.0, last);
    if (pf > pb) {
        edges = vec2<f32>(last, 0.0);
    }
    for (var q = 0u; q < 2u; q = q + 1u) {
        let x = edges[q];
        if (lo < x && x < hi) {
            cuts[m] = x;
            m = m + 1u;
        }
    }
    cuts[m] = pb;
    let len = hi - lo;
    var acc = vec4<f32>(0.0);
    for (var k = 0u; k < m; k = k + 1u) {
        let x1 = cuts[k];
        let x2 = cuts[k + 1u];
        if (x1 == x2) {
            continue;
        }
        var w = 1.0;
        if (len > 0.0) {
            w = abs(x2 - x1) / len;
        }
        let piece = pre_scaled(pre_bilinear(o, last, x1, x2), w);
        acc = acc + (1.0 - acc.w) * piece;
    }
    return acc;
}

// Ends a span of samples (raycast.rs `end_span`): the half step after its last sample joins
// the ray (a whole step where skipped empty space follows, `skip`), the value extrapolated
// linearly from the sample before (a one-sample span: by its slope, and the step before it
// too), lit as that sample was. The cursor then has no sample before the next.
fn end_span(vi: u32, band: u32, cur: ptr<function, Cursor>, acc: vec4<f32>, skip: bool) -> vec4<f32> {
    var out = acc;
    if ((*cur).has_prev) {
        let p = (*cur).prev;
        // The segment's band (`band`) against the sample's own (raycast.rs `end_span`).
        let own = (*cur).prev_band;
        let ratio = f32(1u << min(select(0u, band - own, band > own), 16u));
        // The value half a step and a step past the last sample.
        var half: f32;
        var whole: f32;
        if ((*cur).lead) {
            // A one-sample span: the step before it too, both by its slope.
            let g = (*cur).slope;
            var h: vec4<f32>;
            if ((*cur).gap) {
                h = pre_lookup(vi, own, false, p - g, p);
            } else {
                h = pre_lookup(vi, own, true, p - 0.5 * g, p);
            }
            out = blend(out, apply_light(h, (*cur).prev_light));
            if (ratio == 1.0) {
                half = p + 0.5 * g;
                whole = p + g;
            } else {
                half = p + 0.5 * ratio * g;
                whole = p + ratio * g;
            }
        } else if (ratio == 1.0) {
            half = 1.5 * p - 0.5 * (*cur).before;
            whole = 2.0 * p - (*cur).before;
        } else {
            let g = p - (*cur).before;
            half = p + 0.5 * ratio * g;
            whole = p + ratio * g;
        }
        var rgba: vec4<f32>;
        if (skip) {
            rgba = pre_lookup(vi, band, false, p, whole);
        } else {
            rgba = pre_lookup(vi, band, true, p, half);
        }
        out = blend(out, apply_light(rgba, (*cur).prev_light));
    }
    (*cur).has_prev = false;
    (*cur).lead = false;
    (*cur).gap = skip;
    return out;
}

// Ends volume vi's pre-integrated span at t (a surface, or where the volume begins to overlap
// another, whose mix is post-classified; raycast.rs `end_pre_span`).
fn end_pre_span(vi: u32, cur: ptr<function, Cursor>, t: f32, ray: ptr<function, Ray>) {
    if (!PRE || (vols[vi].flags & VOLUME_PREINTEGRATED) == 0u || !(*cur).has_prev || (*ray).done) {
        return;
    }
    (*ray).acc = end_span(vi, segment_band(t), cur, (*ray).acc, false);
}

// The band of the segment a span ending at t cuts (raycast.rs `segment_band`): the band of
// the first lattice point at or after t.
fn segment_band(t: f32) -> u32 {
    var band = first_band(t);
    loop {
        if (band + 1u >= F.n_bands) { break; }
        let dt = band_dt(band);
        let next = f32(first_k(max(t, band_start(band)), dt)) * dt;
        if (next < band_start(band + 1u)) { break; }
        band = band + 1u;
    }
    return band;
}

struct Ray {
    acc: vec4<f32>,
    done: bool,
    samples: u32,
    skipped: u32,
    terminated: u32,
    hits: u32,
    // This ray's termination threshold (the frame's, or lower under occlusion).
    ert: f32,
}

fn blend(acc: vec4<f32>, s: vec4<f32>) -> vec4<f32> {
    let t = 1.0 - acc.w;
    return acc + t * s;
}

fn first_band(ta: f32) -> u32 {
    var band = 0u;
    loop {
        if (band + 1u < F.n_bands && ta >= band_start(band + 1u)) { band = band + 1u; } else { break; }
    }
    return band;
}

// Marches one volume over [ta, tb) on the lattice.
fn march_one(vi: u32, cur: ptr<function, Cursor>, md: vec3<f32>, d: vec3<f32>, ta: f32, tb: f32, ray: ptr<function, Ray>) {
    var band = first_band(ta);
    var t_start = ta;
    let c = vols[vi].c;
    let pre = PRE && (vols[vi].flags & VOLUME_PREINTEGRATED) != 0u;
    let shading = SHADING && (F.flags & FRAME_SHADING) != 0u;
    loop {
        if (!(t_start < tb) || (*ray).done || band >= F.n_bands) { break; }
        let dt = band_dt(band);
        let seg_end = min(tb, band_end(band));
        var k = first_k(t_start, dt);
        loop {
            let t = f32(k) * dt;
            if (t >= seg_end) { break; }
            if (t >= (*cur).t_exit) {
                locate(vi, cur, t, c + t * md, md);
            }
            if ((*cur).transparent) {
                let nk = max(first_k(min((*cur).t_exit, seg_end), dt), k + 1);
                (*ray).skipped += u32(nk - k);
                k = nk;
                if (pre) { (*ray).acc = end_span(vi, band, cur, (*ray).acc, true); }
                continue;
            }
            let q = c + t * md;
            let s = sample_at(vi, cur, q);
            (*ray).samples += 1u;
            k = k + 1;
            if (is_nan(s)) {
                if (pre) { (*ray).acc = end_span(vi, band, cur, (*ray).acc, false); }
                continue;
            }
            if (pre) {
                var l = vec2<f32>(1.0, 0.0);
                if (shading) { l = light(vi, cur, q, d); }
                if (!(*cur).has_prev) {
                    // A span's first sample: the half step before it waits for the next
                    // sample, which gives the slope to extrapolate it with; should none come,
                    // central differences half a voxel either side stand in.
                    (*cur).lead = true;
                    if (!(*cur).entered) {
                        // The first sample of the volume in this region: a hidden lattice
                        // point before it inside the volume makes its lead a whole step.
                        (*cur).entered = true;
                        let tp = t - dt;
                        if (!(*cur).gap && tp >= (*cur).vol_start) {
                            (*cur).gap = hidden_at(vi, tp, c + tp * md);
                        }
                    }
                    let e = 0.5 / max(abs(md.x), max(abs(md.y), abs(md.z)));
                    let sa = sample_at(vi, cur, q - e * md);
                    let sb = sample_at(vi, cur, q + e * md);
                    // One-sided where a tap falls on no data (raycast.rs).
                    var g = (sb - sa) / (2.0 * e) * dt;
                    if (is_nan(sa)) {
                        g = (sb - s) / e * dt;
                    } else if (is_nan(sb)) {
                        g = (s - sa) / e * dt;
                    }
                    (*cur).slope = select(0.0, g, is_finite(g));
                } else {
                    if ((*cur).lead) {
                        // The half step before the span's first sample (a whole step after
                        // skipped empty space), extrapolated linearly to its front.
                        // In the first sample's own band (raycast.rs).
                        let own = (*cur).prev_band;
                        var h: vec4<f32>;
                        if (own == band) {
                            if ((*cur).gap) {
                                h = pre_lookup(vi, band, false, 2.0 * (*cur).prev - s, (*cur).prev);
                            } else {
                                h = pre_lookup(vi, band, true, 1.5 * (*cur).prev - 0.5 * s, (*cur).prev);
                            }
                        } else {
                            let r = f32(1u << min(band - own, 16u));
                            let g = (s - (*cur).prev) / r;
                            if ((*cur).gap) {
                                h = pre_lookup(vi, own, false, (*cur).prev - g, (*cur).prev);
                            } else {
                                h = pre_lookup(vi, own, true, (*cur).prev - 0.5 * g, (*cur).prev);
                            }
                        }
                        (*ray).acc = blend((*ray).acc, apply_light(h, (*cur).prev_light));
                        (*cur).lead = false;
                        (*cur).gap = false;
                    }
                    let g = pre_lookup(vi, band, false, (*cur).prev, s);
                    (*ray).acc = blend((*ray).acc, apply_light(g, l));
                }
                (*cur).before = (*cur).prev;
                (*cur).prev = s;
                (*cur).prev_band = band;
                (*cur).has_prev = true;
                (*cur).prev_light = l;
                if ((*ray).acc.w >= (*ray).ert) {
                    (*ray).done = true;
                    (*ray).terminated = 1u;
                    return;
                }
                continue;
            }
            var rgba = classify(vi, band, s);
            if (rgba.w <= 0.0) { continue; }
            if (shading) {
                rgba = shade(vi, cur, q, d, rgba);
            }
            (*ray).acc = blend((*ray).acc, rgba);
            if ((*ray).acc.w >= (*ray).ert) {
                (*ray).done = true;
                (*ray).terminated = 1u;
                return;
            }
        }
        // The ray leaves the volume: its span ends half a step after its last sample.
        if (pre && seg_end >= (*cur).span_end) {
            // Past the region, a hidden lattice point inside the volume: a whole step. It
            // cuts the segment to the lattice point that would follow (raycast.rs).
            let seg = segment_band((*cur).span_end);
            let tn = f32(first_k(max((*cur).span_end, band_start(seg)), band_dt(seg))) * band_dt(seg);
            var skip = false;
            if ((*cur).has_prev && tn < (*cur).vol_end) {
                skip = hidden_at(vi, tn, c + tn * md);
            }
            (*ray).acc = end_span(vi, seg, cur, (*ray).acc, skip);
        }
        t_start = seg_end;
        band = band + 1u;
    }
}

// Marches the active_set volumes (bit i of `active_set`) over [ta, tb): classify each, mix, composite.
fn march_mixed(active_set: u32, curs: ptr<function, array<Cursor, 4>>, mds: ptr<function, array<vec3<f32>, 4>>, d: vec3<f32>, ta: f32, tb: f32, ray: ptr<function, Ray>) {
    var band = first_band(ta);
    var t_start = ta;
    loop {
        if (!(t_start < tb) || (*ray).done || band >= F.n_bands) { break; }
        let dt = band_dt(band);
        let seg_end = min(tb, band_end(band));
        var k = first_k(t_start, dt);
        loop {
            let t = f32(k) * dt;
            if (t >= seg_end) { break; }
            k = k + 1;
            var sum = vec3<f32>(0.0);
            var alpha_sum = 0.0;
            var transmit = 1.0;
            for (var vi = 0u; vi < F.n_vols; vi = vi + 1u) {
                if ((active_set & (1u << vi)) == 0u) { continue; }
                let md = (*mds)[vi];
                let q = vols[vi].c + t * md;
                var cur = (*curs)[vi];
                if (t >= cur.t_exit) {
                    locate(vi, &cur, t, q, md);
                }
                if (cur.transparent) {
                    (*curs)[vi] = cur;
                    continue;
                }
                let s = sample_at(vi, &cur, q);
                (*ray).samples += 1u;
                if (is_nan(s)) {
                    (*curs)[vi] = cur;
                    continue;
                }
                var rgba = classify(vi, band, s);
                if (rgba.w <= 0.0) {
                    (*curs)[vi] = cur;
                    continue;
                }
                if (SHADING && (F.flags & FRAME_SHADING) != 0u) {
                    rgba = shade(vi, &cur, q, d, rgba);
                }
                (*curs)[vi] = cur;
                sum = sum + rgba.xyz;
                alpha_sum = alpha_sum + rgba.w;
                transmit = transmit * (1.0 - rgba.w);
            }
            if (alpha_sum <= 0.0) { continue; }
            let a = 1.0 - transmit;
            let w = a / alpha_sum;
            (*ray).acc = blend((*ray).acc, vec4<f32>(sum * w, a));
            if ((*ray).acc.w >= (*ray).ert) {
                (*ray).done = true;
                (*ray).terminated = 1u;
                return;
            }
        }
        t_start = seg_end;
        band = band + 1u;
    }
}

// Cuts [ta, tb) at the volumes' box boundaries and marches each fragment with its active_set set
// (the 1D trace of the BSP over the boxes).
fn march_fragments(spans: ptr<function, array<vec2<f32>, 4>>, curs: ptr<function, array<Cursor, 4>>, mds: ptr<function, array<vec3<f32>, 4>>, d: vec3<f32>, ta: f32, tb: f32, ray: ptr<function, Ray>) {
    var cuts: array<f32, 10>;
    var n = 0u;
    cuts[0] = ta;
    cuts[1] = tb;
    n = 2u;
    for (var i = 0u; i < F.n_vols; i = i + 1u) {
        let s = (*spans)[i];
        if (s.x < s.y) {
            if (s.x > ta && s.x < tb) { cuts[n] = s.x; n = n + 1u; }
            if (s.y > ta && s.y < tb) { cuts[n] = s.y; n = n + 1u; }
        }
    }
    // Insertion sort (at most 10 cuts).
    for (var i = 1u; i < n; i = i + 1u) {
        let x = cuts[i];
        var j = i;
        loop {
            if (j > 0u && cuts[j - 1u] > x) { cuts[j] = cuts[j - 1u]; j = j - 1u; } else { break; }
        }
        cuts[j] = x;
    }
    for (var w = 0u; w + 1u < n; w = w + 1u) {
        let fa = cuts[w];
        let fb = cuts[w + 1u];
        if (fa == fb) { continue; }
        if ((*ray).done) { return; }
        var active_set = 0u;
        var count = 0u;
        var only = 0u;
        for (var i = 0u; i < F.n_vols; i = i + 1u) {
            let s = (*spans)[i];
            if (s.x <= fa && fb <= s.y && s.x < s.y) {
                active_set = active_set | (1u << i);
                count = count + 1u;
                only = i;
            }
        }
        if (count == 1u) {
            var cur = (*curs)[only];
            march_one(only, &cur, (*mds)[only], d, fa, fb, ray);
            (*curs)[only] = cur;
        } else if (count > 1u) {
            // The mix stays post-classified: pre-integrated spans end where it begins.
            for (var i = 0u; i < F.n_vols; i = i + 1u) {
                if ((active_set & (1u << i)) != 0u) {
                    var cur = (*curs)[i];
                    end_pre_span(i, &cur, fa, ray);
                    (*curs)[i] = cur;
                }
            }
            march_mixed(active_set, curs, mds, d, fa, fb, ray);
        }
    }
}

// ---- Horizons -------------------------------------------------------------------------

// [t0, t1] of the ray c + t·d inside the box [lo, hi] (empty: t0 > t1).
fn slab(c: vec3<f32>, d: vec3<f32>, lo: vec3<f32>, hi: vec3<f32>) -> vec2<f32> {
    var t0 = -BIG;
    var t1 = BIG;
    for (var a = 0u; a < 3u; a = a + 1u) {
        if (d[a] == 0.0) {
            if (!(lo[a] <= c[a] && c[a] <= hi[a])) {
                return vec2<f32>(1.0, 0.0);
            }
        } else {
            let ta = (lo[a] - c[a]) / d[a];
            let tb = (hi[a] - c[a]) / d[a];
            t0 = max(t0, min(ta, tb));
            t1 = min(t1, max(ta, tb));
        }
    }
    return vec2<f32>(t0, t1);
}

// slab() with inv = 1 / d precomputed, multiplications for divisions (horizon.rs
// `slab_inv`, used for the tile tree's padded boxes).
fn slab_inv(c: vec3<f32>, d: vec3<f32>, inv: vec3<f32>, lo: vec3<f32>, hi: vec3<f32>) -> vec2<f32> {
    var t0 = -BIG;
    var t1 = BIG;
    for (var a = 0u; a < 3u; a = a + 1u) {
        if (d[a] == 0.0) {
            if (!(lo[a] <= c[a] && c[a] <= hi[a])) {
                return vec2<f32>(1.0, 0.0);
            }
        } else {
            let ta = (lo[a] - c[a]) * inv[a];
            let tb = (hi[a] - c[a]) * inv[a];
            t0 = max(t0, min(ta, tb));
            t1 = min(t1, max(ta, tb));
        }
    }
    return vec2<f32>(t0, t1);
}

struct Roots {
    n: u32,
    r: vec2<f32>,
}

// Rust's f32::signum: ±1 by the sign bit.
fn signum(x: f32) -> f32 {
    return select(1.0, -1.0, (bitcast<u32>(x) & 0x80000000u) != 0u);
}

// Real roots of a s² + b s + c = 0 in [lo, hi), ascending.
fn roots_in(a: f32, b: f32, c: f32, lo: f32, hi: f32) -> Roots {
    var out = Roots(0u, vec2<f32>(0.0));
    var cand = vec2<f32>(0.0);
    var nc = 0u;
    // Linear only when it is (horizon.rs `roots_in`).
    if (a == 0.0) {
        if (b != 0.0) {
            cand[0] = -c / b;
            nc = 1u;
        }
    } else {
        let disc = b * b - 4.0 * a * c;
        if (disc < 0.0) {
            return out;
        }
        // The numerically stable pair (no cancellation between b and the root).
        let q = -0.5 * (b + signum(b) * sqrt(disc));
        var s1 = 0.0;
        var s2 = 0.0;
        if (q != 0.0) {
            s1 = q / a;
            s2 = c / q;
        } else if (c != 0.0) {
            return out; // b = 0 and a·c underflowed (horizon.rs `roots_in`)
        }
        cand = vec2<f32>(min(s1, s2), max(s1, s2));
        nc = select(2u, 1u, cand[1] == cand[0]);
    }
    for (var i = 0u; i < nc; i = i + 1u) {
        let s = cand[i];
        if (is_finite(s) && s >= lo && s < hi) {
            out.r[out.n] = s;
            out.n = out.n + 1u;
        }
    }
    return out;
}

// Keeps the crossing in the ray's sorted list (after equal ones, as a stable sort would);
// a full list drops its farthest. `hits_full` says the list filled (the ray then searches
// again from its farthest crossing: cast_rays).
fn push_hit(t: f32, c: vec4<f32>) {
    var j = n_hits;
    if (j == MAX_HITS) {
        if (t >= hit_t[MAX_HITS - 1u]) {
            return;
        }
        j = MAX_HITS - 1u;
    } else {
        n_hits = n_hits + 1u;
    }
    loop {
        if (j > 0u && hit_t[j - 1u] > t) {
            hit_t[j] = hit_t[j - 1u];
            hit_c[j] = hit_c[j - 1u];
            j = j - 1u;
        } else {
            break;
        }
    }
    hit_t[j] = t;
    hit_c[j] = c;
    // Full: the searches now stop at the farthest crossing (h_leaf), so there may be more.
    if (n_hits == MAX_HITS) {
        hits_full = true;
    }
}

// Volume `vi`'s straight transfer-function colour of a (non-NaN) value.
fn straight_color(vi: u32, value: f32) -> vec4<f32> {
    let v = &vols[vi];
    let x = clamp(value * (*v).tf_scale + (*v).tf_offset, 0.0, (*v).tf_last);
    let i = min(u32(x), TF_SIZE - 2u);
    let f = x - f32(i);
    let ca = tf[(*v).straight_base + i];
    let cb = tf[(*v).straight_base + i + 1u];
    return ca + f * (cb - ca);
}

// Volume `vi`'s straight colour at the camera-relative point t·d, its page requested at the
// level the distance calls for (volume.rs `color_at`); w = 0 where there is none (outside the
// volume, page not resident yet, no data).
fn volume_color(vi: u32, t: f32, d: vec3<f32>) -> vec4<f32> {
    let md = index_dir(vi, d);
    let q = vols[vi].c + t * md;
    let hi = vols[vi].hi;
    if (!(q.x >= -0.5 && q.x < hi.x && q.y >= -0.5 && q.y < hi.y && q.z >= -0.5 && q.z < hi.z)) {
        return vec4<f32>(0.0);
    }
    let c = straight_at(vi, t, q, md);
    if (c.w < 0.0) {
        return vec4<f32>(0.0);
    }
    return vec4<f32>(c.xyz, 1.0);
}

// The straight colour of volume `vi`'s value at index position q (ray distance t, direction
// md), its page located and requested even where the transfer function hides it
// (volume.rs `straight_at`); w = -1 where the page is not resident yet or holds no data.
fn straight_at(vi: u32, t: f32, q: vec3<f32>, md: vec3<f32>) -> vec4<f32> {
    var cur = new_cursor();
    locate_page(vi, &cur, t, q, md, false);
    if (cur.transparent) {
        return vec4<f32>(-1.0);
    }
    let value = sample_at(vi, &cur, q);
    if (is_nan(value)) {
        return vec4<f32>(-1.0);
    }
    return straight_color(vi, value);
}

// The ray's crossings of volume `vi`'s slices inside [t0, t1) as surface hits in the
// straight transfer-function colours (volume.rs `slice_hits`, operation for operation).
fn slice_hits(vi: u32, md: vec3<f32>, t0: f32, t1: f32) {
    let v = vols[vi];
    for (var s = 0u; s < v.n_slices; s = s + 1u) {
        let rec = tf[v.slice_base + s];
        let a = u32(rec.x);
        if (md[a] == 0.0) {
            continue;
        }
        let idx = rec.y;
        let t = (idx - v.c[a]) / md[a];
        if (!(t >= t0 && t < t1)) {
            continue;
        }
        var q = v.c + t * md;
        q[a] = idx;
        var inside = true;
        for (var k = 0u; k < 3u; k = k + 1u) {
            if (k != a && !(q[k] >= -0.5 && q[k] < v.hi[k])) {
                inside = false;
            }
        }
        if (!inside) {
            continue;
        }
        // Not resident yet, or no data: nothing this round.
        let c = straight_at(vi, t, q, md);
        if (c.w < 0.0) {
            continue;
        }
        let o = rec.z;
        push_hit(t, vec4<f32>(c.xyz * o, o));
    }
}

fn h_level_at(hi: u32, t: f32) -> u32 {
    var l = 0u;
    loop {
        if (l + 1u < hors[hi].n_levels && t >= hors[hi].level_t[l + 1u]) { l = l + 1u; } else { break; }
    }
    return l;
}

// Lateral footprint of tile b at `level` in level-0 node coordinates (lo.xy, hi.xy):
// [b·core·2^level, (b + 1)·core·2^level), the same at every level, so a tile's footprint
// is exactly its children's (horizon.rs `footprint`).
fn footprint(hi: u32, level: u32, b: vec2<u32>) -> vec4<f32> {
    let w = f32(hors[hi].core) * ldexp(1.0, i32(level));
    return vec4<f32>(
        f32(b.x) * w,
        f32(b.y) * w,
        f32(b.x + 1u) * w,
        f32(b.y + 1u) * w,
    );
}

// Index of tile b at `level` in the horizon's own page table.
fn h_index(hi: u32, level: u32, b: vec2<u32>) -> u32 {
    let li = levels[hors[hi].level_base + level];
    return li.x + b.y * li.y + b.x;
}

fn nan_f32() -> f32 {
    return bitcast<f32>(0x7fc00000u);
}

// Colour of the surface at height h with index-space slopes (hu, hv) at level scale sr.
fn shade_horizon(hi: u32, d: vec3<f32>, hu: f32, hv: f32, sr: f32, h: f32) -> vec3<f32> {
    let hz = &hors[hi];
    var base = (*hz).color;
    if (((*hz).flags & HORIZON_DEPTH_MAP) != 0u) {
        let lo = (*hz).depth_lo;
        let top = (*hz).depth_hi;
        var x = 0.5;
        if (top > lo) {
            x = (h - lo) / (top - lo);
        }
        let n = (*hz).map_len;
        let s = clamp(x, 0.0, 1.0) * f32(n - 1u);
        let i = min(u32(s), n - 2u);
        let f = s - f32(i);
        let a = tf[(*hz).map_base + i].xyz;
        let b = tf[(*hz).map_base + i + 1u].xyz;
        base = a + f * (b - a);
    }
    if (!LIGHTING || ((*hz).flags & HORIZON_LIGHTING) == 0u) {
        return base;
    }
    // Normal in index space (per level-0 node), then to camera space by Mᵀ.
    let ni = vec3<f32>(-hu * sr, -hv * sr, 1.0);
    let n = mul_cols((*hz).m0, (*hz).m1, (*hz).m2, ni);
    let len = sqrt(n.x * n.x + n.y * n.y + n.z * n.z);
    var cosv = 1.0;
    if (len > 0.0 && is_finite(len)) {
        cosv = abs((n.x * d.x + n.y * d.y + n.z * d.z) / len);
    }
    let k = 0.25 + 0.75 * cosv;
    return base * k;
}

// Height at level-r node (i, j) of the tile held in the slot at `base` whose first node is
// `off`; NaN outside the tile.
fn h_node(base: u32, p: i32, off: vec2<i32>, i: i32, j: i32) -> f32 {
    let li = i - off.x;
    let lj = j - off.y;
    if (li < 0 || lj < 0 || li >= p || lj >= p) {
        return nan_f32();
    }
    return hpool[base + u32(lj * p + li)];
}

// Walks the cells of tile b at `level` from `ta` on, using the finest resident data;
// crossings from `keep_from` on go to the hit list (those before it were composited by an
// earlier batch: they only set `h_last`), an opaque one lowers `limit`, and so does a full
// list (to its farthest crossing: anything beyond is dropped until the next batch).
fn h_leaf(hi: u32, level: u32, b: vec2<u32>, d: vec3<f32>, md: vec3<f32>, ta: f32, keep_from: f32, limit: ptr<function, f32>) {
    let hz = &hors[hi];
    let e = table[(*hz).table_base + h_index(hi, level, b)];
    if (e == NOT_RESIDENT) {
        return;
    }
    let r = (e >> 24u) & LEVEL_MASK;
    let slot = e & SLOT_MASK;
    let k = r - level;
    let br = vec2<u32>(b.x >> k, b.y >> k);
    // Clip to this tile's own footprint (exact, not padded), within the data.
    let fp = footprint(hi, level, b);
    let dims = (*hz).dims;
    let last = vec2<f32>(f32(dims.x) - 1.0, f32(dims.y) - 1.0);
    // A ray with no motion along an axis is in the tile or not: half-open, so one on the
    // edge between two tiles is walked by one of them (horizon.rs `leaf`).
    let c = (*hz).c;
    if ((md.x == 0.0 && fp.z < last.x && c.x >= fp.z) || (md.y == 0.0 && fp.w < last.y && c.y >= fp.w)) {
        return;
    }
    let flo = vec2<f32>(max(fp.x, 0.0), max(fp.y, 0.0));
    let fhi = vec2<f32>(min(fp.z, last.x), min(fp.w, last.y));
    // Also clip to the height range of the data used, so steep rays walk few cells.
    let zb = hbounds[(*hz).bounds_base + h_index(hi, r, br)];
    if (!(zb.x <= zb.y)) {
        return;
    }
    // Padded past the rounding of heights relative to the eye too (horizon.rs `leaf`).
    let eps = 1e-4 * (1.0 + max(abs(zb.x), abs(zb.y))) + abs(c.z) * (1.0 / 1048576.0);
    let u = slab(c, md, vec3<f32>(flo, zb.x - eps), vec3<f32>(fhi, zb.y + eps));
    let t_lo = max(max(u.x, ta), 0.0);
    let t_hi = min(u.y, *limit);
    if (t_lo >= t_hi) {
        return;
    }
    // Ray in level-r node coordinates.
    let sr = ldexp(1.0, -i32(r));
    let cr = vec3<f32>((c.x + 0.5) * sr - 0.5, (c.y + 0.5) * sr - 0.5, c.z);
    let dr = vec3<f32>(md.x * sr, md.y * sr, md.z);
    var nodes = dims;
    for (var l = 0u; l < r; l = l + 1u) {
        nodes = (nodes + vec2<u32>(1u)) / 2u;
    }
    let nodes_r = vec2<i32>(nodes);
    let p = i32((*hz).page);
    let core = i32((*hz).core);
    let border = i32((*hz).border);
    let off = vec2<i32>(i32(br.x) * core - border, i32(br.y) * core - border);
    let base = (*hz).pool_base + slot * u32(p * p);
    let opacity = (*hz).opacity;
    // 2D DDA over level-r cells.
    var cell = vec2<i32>(i32(floor(cr.x + t_lo * dr.x)), i32(floor(cr.y + t_lo * dr.y)));
    let step = vec2<i32>(select(-1, 1, dr.x > 0.0), select(-1, 1, dr.y > 0.0));
    var t_cell = t_lo;
    var guard = 0u;
    loop {
        if (!(t_cell < t_hi) || guard >= (1u << 20u)) { break; }
        guard = guard + 1u;
        var tx = BIG;
        if (dr.x != 0.0) {
            tx = (f32(select(cell.x, cell.x + 1, dr.x > 0.0)) - cr.x) / dr.x;
        }
        var ty = BIG;
        if (dr.y != 0.0) {
            ty = (f32(select(cell.y, cell.y + 1, dr.y > 0.0)) - cr.y) / dr.y;
        }
        let t_next = min(min(tx, ty), t_hi);
        let i = cell.x;
        let j = cell.y;
        if (i >= 0 && j >= 0 && i + 1 < nodes_r.x && j + 1 < nodes_r.y && t_next > t_cell) {
            let h00 = h_node(base, p, off, i, j);
            let h10 = h_node(base, p, off, i + 1, j);
            let h01 = h_node(base, p, off, i, j + 1);
            let h11 = h_node(base, p, off, i + 1, j + 1);
            if (!(is_nan(h00) || is_nan(h10) || is_nan(h01) || is_nan(h11))) {
                let z0 = cr.z + t_cell * dr.z;
                let z1 = cr.z + t_next * dr.z;
                let hmin = min(min(h00, h10), min(h01, h11));
                let hmax = max(max(h00, h10), max(h01, h11));
                // A cull only, padded like the height clip (see horizon.rs).
                if (min(z0, z1) <= hmax + eps && max(z0, z1) >= hmin - eps) {
                    // Solve relative to where the ray enters this cell (independent of where
                    // the region clipped it): the same crossing gets the same t everywhere.
                    var ex = -BIG;
                    if (dr.x != 0.0) {
                        ex = (f32(select(i + 1, i, dr.x > 0.0)) - cr.x) / dr.x;
                    }
                    var ey = -BIG;
                    if (dr.y != 0.0) {
                        ey = (f32(select(j + 1, j, dr.y > 0.0)) - cr.y) / dr.y;
                    }
                    // Never before the ray's origin, which no region moves either: a
                    // vertical ray enters no cell (-BIG), a nearly vertical one enters its
                    // cells far behind the eye (horizon.rs).
                    let t_org = max(max(ex, ey), 0.0);
                    let zo = cr.z + t_org * dr.z;
                    let u0 = cr.x + t_org * dr.x - f32(i);
                    let v0 = cr.y + t_org * dr.y - f32(j);
                    let a = h10 - h00;
                    let bb = h01 - h00;
                    let cc = h00 - h10 - h01 + h11;
                    let qa = -cc * dr.x * dr.y;
                    let qb = dr.z - a * dr.x - bb * dr.y - cc * (u0 * dr.y + v0 * dr.x);
                    let qc = zo - h00 - a * u0 - bb * v0 - cc * u0 * v0;
                    // Every root, then one test on the absolute t (as on the CPU: bounds
                    // relative to t_org can disagree with t_org + s by a rounding, and a
                    // crossing on a region face was lost to both regions).
                    let roots = roots_in(qa, qb, qc, -BIG, BIG);
                    // Crossings of an earlier cell (not this one's: a grazing ray's two).
                    let prev = h_last;
                    let end = t_next + abs(t_next) * EDGE_REL;
                    for (var q = 0u; q < roots.n; q = q + 1u) {
                        let sroot = roots.r[q];
                        let t = t_org + sroot;
                        if (t < t_cell || t >= end || t < ta || t >= *limit) {
                            continue;
                        }
                        if (abs(t - prev) <= abs(t) * EDGE_REL) {
                            continue; // the last cell kept it
                        }
                        h_last = t;
                        if (t < keep_from) {
                            continue; // an earlier batch's
                        }
                        let uu = clamp(u0 + sroot * dr.x, 0.0, 1.0);
                        let vv = clamp(v0 + sroot * dr.y, 0.0, 1.0);
                        let h = h00 + a * uu + bb * vv + cc * uu * vv;
                        let rgb = shade_horizon(hi, d, a + cc * vv, bb + cc * uu, sr, h);
                        var hc = vec4<f32>(rgb * opacity, opacity);
                        let av = (*hz).attr_vol;
                        if (av != NO_VOLUME) {
                            // The volume's colour where the surface lies (raycast.rs
                            // `start_with`); the no-data colour where it has none.
                            var vc = volume_color(av, t, d);
                            if (vc.w == 0.0) {
                                vc = vec4<f32>(tf[(*hz).map_base].xyz, 1.0);
                            }
                            hc = hc * vec4<f32>(vc.xyz, 1.0);
                        }
                        push_hit(t, hc);
                        if (opacity >= 1.0) {
                            // Nothing behind an opaque surface is visible.
                            *limit = min(*limit, t);
                        }
                        if (n_hits == MAX_HITS) {
                            *limit = min(*limit, hit_t[MAX_HITS - 1u]);
                        }
                    }
                }
            }
        }
        t_cell = t_next;
        if (tx <= ty) {
            cell.x = cell.x + step.x;
        } else {
            cell.y = cell.y + step.y;
        }
    }
}

// All crossings of the ray t·d, t in [keep_from, tb), with horizon `hi`, walked from ta
// (≤ keep_from: a later batch walks from a little before its start, see cast_rays): a
// front-to-back descent of the min-max tile tree to the level the footprint calls for; the
// tiles reached are counted in the feedback. Returns the nearest opaque crossing, the
// farthest of a full list, or tb (horizon.rs `intersect`).
fn intersect_horizon(hi: u32, d: vec3<f32>, ta: f32, keep_from: f32, tb: f32) -> f32 {
    let hz = &hors[hi];
    let md = mul_rows((*hz).m0, (*hz).m1, (*hz).m2, d);
    // Components where md is 0 are never used (slab_inv tests d == 0 first).
    let inv = vec3<f32>(1.0) / select(md, vec3<f32>(1.0), md == vec3<f32>(0.0));
    let c = (*hz).c;
    var limit = tb;
    if (n_hits == MAX_HITS) {
        limit = min(limit, hit_t[MAX_HITS - 1u]);
    }
    h_last = -BIG;
    var stack: array<vec3<u32>, STACK>;
    stack[0] = vec3<u32>((*hz).n_levels - 1u, 0u, 0u);
    var sp = 1u;
    loop {
        if (sp == 0u) { break; }
        sp = sp - 1u;
        let level = stack[sp].x;
        let b = stack[sp].yz;
        let idx = h_index(hi, level, b);
        let zb = hbounds[(*hz).bounds_base + idx];
        if (!(zb.x <= zb.y)) {
            continue; // all holes
        }
        let s = ldexp(1.0, i32(level));
        let fp = footprint(hi, level, b);
        // Pad by one cell of this level (horizon.rs `tile_boxes`): no rounding of this test
        // culls what the leaf's exact clip keeps. A flat tile gets a little thickness so the
        // slab test cannot lose it to rounding.
        // Plus 8 ulps of the eye's height (horizon.rs `z_pad`).
        let eps = 1e-4 * (1.0 + max(abs(zb.x), abs(zb.y))) + abs(c.z) * (1.0 / 1048576.0);
        let e = slab_inv(c, md, inv, vec3<f32>(fp.x - s, fp.y - s, zb.x - eps), vec3<f32>(fp.z + s, fp.w + s, zb.y + eps));
        // Strict (horizon.rs `visit`: a flat tile's slab of no thickness seen from afar).
        if (max(e.x, ta) > min(e.y, limit) || e.y < 0.0) {
            continue;
        }
        // The LOD decision uses the unclipped entry, so it does not depend on the region.
        let want = h_level_at(hi, max(e.x, 0.0));
        if (level == 0u || level <= want) {
            atomicAdd(&feedback[(*hz).table_base + idx], 1u);
            // A tile whose own cells are mostly holes is drawn by its children (horizon.rs
            // `visit`; it stays requested, so its flag stays known).
            if (level == 0u || (table[(*hz).table_base + idx] & ENTRY_FRAGMENTED) == 0u) {
                h_leaf(hi, level, b, d, md, ta, keep_from, &limit);
                continue;
            }
        }
        // Children sorted front to back (stable) by where the ray crosses the split lines
        // (horizon.rs `visit`: a far-side child is entered at its split line), pushed
        // farthest first.
        let lb = levels[(*hz).level_base + level - 1u].yz;
        let split = footprint(hi, level - 1u, vec2<u32>(2u * b.x + 1u, 2u * b.y + 1u)).xy;
        var cross = vec2<f32>(BIG, BIG);
        for (var a = 0u; a < 2u; a = a + 1u) {
            if (md[a] != 0.0) {
                cross[a] = (split[a] - c[a]) / md[a];
            }
        }
        var kt: array<f32, 4>;
        var kb: array<vec2<u32>, 4>;
        var n = 0u;
        for (var dy = 0u; dy < 2u; dy = dy + 1u) {
            for (var dx = 0u; dx < 2u; dx = dx + 1u) {
                let cb = vec2<u32>(2u * b.x + dx, 2u * b.y + dy);
                if (cb.x < lb.x && cb.y < lb.y) {
                    let far_x = select(dx == 0u, dx == 1u, md.x >= 0.0);
                    let far_y = select(dy == 0u, dy == 1u, md.y >= 0.0);
                    let t0 = max(select(-BIG, cross.x, far_x), select(-BIG, cross.y, far_y));
                    var j = n;
                    loop {
                        if (j > 0u && kt[j - 1u] > t0) {
                            kt[j] = kt[j - 1u];
                            kb[j] = kb[j - 1u];
                            j = j - 1u;
                        } else {
                            break;
                        }
                    }
                    kt[j] = t0;
                    kb[j] = cb;
                    n = n + 1u;
                }
            }
        }
        for (var q = 0u; q < n; q = q + 1u) {
            if (sp < STACK) {
                stack[sp] = vec3<u32>(level - 1u, kb[n - 1u - q]);
                sp = sp + 1u;
            }
        }
    }
    return limit;
}

fn sanitize(c: vec4<f32>) -> vec4<f32> {
    if (is_finite(c.x) && is_finite(c.y) && is_finite(c.z) && is_finite(c.w)) {
        return vec4<f32>(max(c.xyz, vec3<f32>(0.0)), clamp(c.w, 0.0, 1.0));
    }
    return vec4<f32>(0.0);
}

fn add64(lo: u32, v: u32) {
    let old = atomicAdd(&stats[lo], v);
    if (old + v < old) {
        atomicAdd(&stats[lo + 1u], 1u);
    }
}

fn new_cursor() -> Cursor {
    return Cursor(0u, -BIG, true, 0u, 1.0, vec3<f32>(0.0), vec3<f32>(0.0), false, 0.0, 0.0, 0u, false, false, 0.0, vec2<f32>(1.0, 0.0), BIG, -BIG, BIG, false);
}

@compute @workgroup_size(8, 8, 1)
fn cast_rays(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    if (lid == 0u) {
        atomicStore(&wg_samples, 0u);
        atomicStore(&wg_skipped, 0u);
        atomicStore(&wg_terminated, 0u);
        atomicStore(&wg_rays, 0u);
        atomicStore(&wg_hits, 0u);
    }
    workgroupBarrier();
    var ray = Ray(vec4<f32>(0.0), false, 0u, 0u, 0u, 0u, F.ert);
    let inside = gid.x < F.rect_w && gid.y < F.rect_h;
    var casts = inside;
    if (inside && F.occl_block > 0u) {
        let x = F.rect_x + gid.x;
        let y = F.rect_y + gid.y;
        let cols = (F.width + F.occl_block - 1u) / F.occl_block;
        ray.ert = occl[(y / F.occl_block) * cols + x / F.occl_block];
        casts = ray.ert >= 0.0;
    }
    if (casts) {
        // Image pixel -> the frustum's plane (a wall's tiles skip the mullions).
        let iy = F.rect_y + gid.y;
        let t = iy / F.tile_h;
        let x = (t % F.tile_cols) * F.pitch_x + F.rect_x + gid.x;
        let y = (t / F.tile_cols) * F.pitch_y + iy - t * F.tile_h;
        let fx = f32(x) + 0.5;
        let fy = f32(y) + 0.5;
        let d0 = F.dir00 + fx * F.du + fy * F.dv;
        let l = sqrt(d0.x * d0.x + d0.y * d0.y + d0.z * d0.z);
        let d = d0 / l;
        let tt = clip_region(F.region_lo, F.region_hi, d);
        if (tt.x < tt.y) {
            var curs: array<Cursor, 4>;
            var mds: array<vec3<f32>, 4>;
            var spans: array<vec2<f32>, 4>;
            for (var i = 0u; i < F.n_vols; i = i + 1u) {
                let md = index_dir(i, d);
                let iv = interval(i, md);
                mds[i] = md;
                spans[i] = vec2<f32>(max(iv.x, tt.x), min(iv.y, tt.y));
                // A volume whose transfer function shows nothing is not marched (raycast.rs).
                if ((vols[i].flags & VOLUME_INVISIBLE) != 0u) {
                    spans[i] = vec2<f32>(0.0, 0.0);
                }
                curs[i] = new_cursor();
                curs[i].span_end = spans[i].y;
                curs[i].vol_start = iv.x;
                curs[i].vol_end = iv.y;
            }
            // The surfaces' crossings in batches of at most MAX_HITS, nearest first: a
            // search whose list overflowed ends its batch before its farthest crossing, and
            // the next batch searches again from there. Every crossing is composited, as on
            // the CPU, however many the ray meets (only more than MAX_HITS at one t would
            // be cut to MAX_HITS).
            var search_from = tt.x;
            var cur_t = tt.x;
            loop {
                var nh = 0u;
                var batch_end = tt.y;
                if (HORIZONS || SLICES) {
                    n_hits = 0u;
                    hits_full = false;
                    // Slices first, then each horizon only up to the nearest opaque surface
                    // found so far (raycast.rs `start`).
                    var limit = tt.y;
                    if (SLICES) {
                        for (var i = 0u; i < F.n_vols; i = i + 1u) {
                            slice_hits(i, mds[i], search_from, tt.y);
                        }
                        for (var k = 0u; k < n_hits; k = k + 1u) {
                            if (hit_c[k].w >= 1.0) {
                                limit = min(limit, hit_t[k]);
                            }
                        }
                    }
                    if (HORIZONS) {
                        // A later batch walks the cells from a little before its start, so
                        // that a crossing on a cell edge the last batch ended at is solved
                        // in the same cell as before (h_leaf keeps only those from
                        // search_from on, and drops the next cell's copy).
                        var walk_from = search_from;
                        if (search_from > tt.x) {
                            walk_from = max(tt.x, search_from - 2.0 * abs(search_from) * EDGE_REL);
                        }
                        for (var h = 0u; h < F.n_hors; h = h + 1u) {
                            limit = min(limit, intersect_horizon(h, d, walk_from, search_from, limit));
                        }
                    }
                    nh = n_hits;
                    if (hits_full) {
                        // This batch ends at its farthest crossing, which (with any equal to
                        // it) the next batch finds again; unless every crossing kept lies
                        // there, and then they are all this batch's.
                        let far = hit_t[nh - 1u];
                        var m = nh;
                        loop {
                            if (m > 0u && hit_t[m - 1u] >= far) { m = m - 1u; } else { break; }
                        }
                        if (m > 0u) {
                            nh = m;
                            batch_end = far;
                        } else {
                            batch_end = bitcast<f32>(bitcast<u32>(far) + 1u);
                        }
                    }
                }
                // March the volumes up to each crossing, composite it, go on.
                var next = 0u;
                loop {
                    var next_hit = BIG;
                    if ((HORIZONS || SLICES) && next < nh) {
                        next_hit = hit_t[next];
                    }
                    let seg_end = min(min(next_hit, tt.y), batch_end);
                    if (seg_end > cur_t) {
                        if (MULTI) {
                            march_fragments(&spans, &curs, &mds, d, cur_t, seg_end, &ray);
                        } else if (F.n_vols == 1u) {
                            let a = max(spans[0].x, cur_t);
                            let b = min(spans[0].y, seg_end);
                            if (a < b) {
                                var cur = curs[0];
                                march_one(0u, &cur, mds[0], d, a, b, &ray);
                                curs[0] = cur;
                            }
                        }
                        cur_t = seg_end;
                    }
                    if (ray.done) { break; }
                    if ((HORIZONS || SLICES) && next < nh && next_hit < tt.y && seg_end >= next_hit) {
                        // Pre-integrated spans end at the surface (an opaque one ends the ray).
                        if (PRE) {
                            for (var i = 0u; i < F.n_vols; i = i + 1u) {
                                var cur = curs[i];
                                end_pre_span(i, &cur, next_hit, &ray);
                                curs[i] = cur;
                            }
                        }
                        ray.acc = blend(ray.acc, hit_c[next]);
                        ray.hits = ray.hits + 1u;
                        next = next + 1u;
                        if (ray.acc.w >= ray.ert) {
                            ray.done = true;
                            ray.terminated = 1u;
                            break;
                        }
                        cur_t = max(cur_t, next_hit);
                        continue;
                    }
                    break;
                }
                // (The second test only guards against a GPU that flushes the denormal one
                // ulp past 0 to 0.)
                if (ray.done || !(batch_end < tt.y) || !(batch_end > search_from)) { break; }
                search_from = batch_end;
            }
        }
        atomicAdd(&wg_samples, ray.samples);
        atomicAdd(&wg_skipped, ray.skipped);
        atomicAdd(&wg_terminated, ray.terminated);
        atomicAdd(&wg_rays, 1u);
        atomicAdd(&wg_hits, ray.hits);
    }
    // A ray not cast leaves its pixel transparent.
    if (inside) {
        out_px[gid.y * F.rect_w + gid.x] = sanitize(ray.acc);
    }
    workgroupBarrier();
    if (lid == 0u) {
        add64(0u, atomicLoad(&wg_samples));
        add64(2u, atomicLoad(&wg_skipped));
        atomicAdd(&stats[4], atomicLoad(&wg_terminated));
        atomicAdd(&stats[5], atomicLoad(&wg_rays));
        atomicAdd(&stats[6], atomicLoad(&wg_hits));
    }
}

// Feedback compaction: every counter that rays raised becomes one (entry, coverage) pair of
// a dense list, and is cleared for the next frame. Only the list crosses the bus.
// The counters are `feedback` (binding 7), bound to exactly the frame's entries.
@group(0) @binding(10) var<storage, read_write> fb_list: array<vec2<u32>>;
@group(0) @binding(11) var<storage, read_write> fb_len: array<atomic<u32>, 1>;

@compute @workgroup_size(64, 1, 1)
fn compact(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 64u;
    if (i >= arrayLength(&feedback)) {
        return;
    }
    let n = atomicExchange(&feedback[i], 0u);
    if (n != 0u) {
        let j = atomicAdd(&fb_len[0], 1u);
        fb_list[j] = vec2<u32>(i, n);
    }
}
