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
// Effects are pipeline-overridable constants, so a scene without them runs no code for them:
// SHADING (gradient shading), MULTI (several volumes mixed per sample).

const TF_SIZE: u32 = 1024u;
const MAX_VOLS: u32 = 4u;
const NOT_RESIDENT: u32 = 0xffffffffu;
const SLOT_MASK: u32 = 0xffffffu;
const BIG: f32 = 3.0e38; // stands in for +infinity (WGSL has no infinity literal)

override SHADING: bool = false;
override MULTI: bool = false;

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
    _pad0: u32,
    _pad1: u32,
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
    _pad0: u32,
    _pad1: u32,
    level_t: array<f32, 16>,
}

struct Cursor {
    level: u32,
    t_exit: f32,
    transparent: bool,
    base: u32,
    s: f32,
    o: vec3<f32>,
}

@group(0) @binding(0) var<uniform> F: Frame;
@group(0) @binding(1) var<storage, read> vols: array<Volume>;
// x = first entry of the level in its data set's table, yzw = bricks per axis.
@group(0) @binding(2) var<storage, read> levels: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> table: array<u32>;
// One bit per page-table entry: nothing in the page is visible under the transfer function.
@group(0) @binding(4) var<storage, read> transparent: array<u32>;
@group(0) @binding(5) var<storage, read> tf: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read> pool: array<f32>;
@group(0) @binding(7) var<storage, read_write> feedback: array<atomic<u32>>;
@group(0) @binding(8) var<storage, read_write> out_px: array<vec4<f32>>;
// samples lo/hi, skipped lo/hi, terminated, rays.
@group(0) @binding(9) var<storage, read_write> stats: array<atomic<u32>, 8>;

var<workgroup> wg_samples: atomic<u32>;
var<workgroup> wg_skipped: atomic<u32>;
var<workgroup> wg_terminated: atomic<u32>;
var<workgroup> wg_rays: atomic<u32>;

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

fn index_dir(vi: u32, d: vec3<f32>) -> vec3<f32> {
    let v = &vols[vi];
    return vec3<f32>(
        (*v).m0.x * d.x + (*v).m0.y * d.y + (*v).m0.z * d.z,
        (*v).m1.x * d.x + (*v).m1.y * d.y + (*v).m1.z * d.z,
        (*v).m2.x * d.x + (*v).m2.y * d.y + (*v).m2.z * d.z,
    );
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
    if (((transparent[g >> 5u] >> (g & 31u)) & 1u) != 0u) {
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
    (*cur).base = vols[vi].pool_base + slot * p * p * p;
    (*cur).s = sr;
    let border = vols[vi].border;
    for (var a = 0u; a < 3u; a = a + 1u) {
        let br = f32(b[a] >> k);
        (*cur).o[a] = 0.5 * sr - 0.5 - br * core + border;
    }
}

// Trilinear interpolation in a p³ page at local coordinates within [0, p − 1).
fn trilinear(base: u32, p: u32, x: f32, y: f32, z: f32) -> f32 {
    let xi = u32(x);
    let yi = u32(y);
    let zi = u32(z);
    let fx = x - f32(xi);
    let fy = y - f32(yi);
    let fz = z - f32(zi);
    let i = base + (zi * p + yi) * p + xi;
    let sy = p;
    let sz = p * p;
    let c00 = pool[i] + fx * (pool[i + 1u] - pool[i]);
    let c10 = pool[i + sy] + fx * (pool[i + sy + 1u] - pool[i + sy]);
    let c01 = pool[i + sz] + fx * (pool[i + sz + 1u] - pool[i + sz]);
    let c11 = pool[i + sz + sy] + fx * (pool[i + sz + sy + 1u] - pool[i + sz + sy]);
    let c0 = c00 + fy * (c10 - c00);
    let c1 = c01 + fy * (c11 - c01);
    return c0 + fz * (c1 - c0);
}

fn local(vi: u32, cur: ptr<function, Cursor>, q: vec3<f32>, dx: vec3<f32>) -> vec3<f32> {
    let maxc = f32(vols[vi].page - 1u) - 1e-3;
    return clamp(q * (*cur).s + (*cur).o + dx, vec3<f32>(0.0), vec3<f32>(maxc));
}

fn sample_at(vi: u32, cur: ptr<function, Cursor>, q: vec3<f32>) -> f32 {
    let l = local(vi, cur, q, vec3<f32>(0.0));
    return trilinear((*cur).base, vols[vi].page, l.x, l.y, l.z);
}

fn tap(vi: u32, cur: ptr<function, Cursor>, q: vec3<f32>, dx: vec3<f32>) -> f32 {
    let maxc = f32(vols[vi].page - 1u) - 1e-3;
    let l = clamp(q * (*cur).s + (*cur).o + dx, vec3<f32>(0.0), vec3<f32>(maxc));
    return trilinear((*cur).base, vols[vi].page, l.x, l.y, l.z);
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

// Headlight Blinn-Phong from the index-space gradient (central differences).
fn shade(vi: u32, cur: ptr<function, Cursor>, q: vec3<f32>, d: vec3<f32>, rgba: vec4<f32>) -> vec4<f32> {
    let g = vec3<f32>(
        tap(vi, cur, q, vec3<f32>(1.0, 0.0, 0.0)) - tap(vi, cur, q, vec3<f32>(-1.0, 0.0, 0.0)),
        tap(vi, cur, q, vec3<f32>(0.0, 1.0, 0.0)) - tap(vi, cur, q, vec3<f32>(0.0, -1.0, 0.0)),
        tap(vi, cur, q, vec3<f32>(0.0, 0.0, 1.0)) - tap(vi, cur, q, vec3<f32>(0.0, 0.0, -1.0)),
    );
    let m0 = vols[vi].m0;
    let m1 = vols[vi].m1;
    let m2 = vols[vi].m2;
    let n = vec3<f32>(
        m0.x * g.x + m1.x * g.y + m2.x * g.z,
        m0.y * g.x + m1.y * g.y + m2.y * g.z,
        m0.z * g.x + m1.z * g.y + m2.z * g.z,
    );
    let len = sqrt(n.x * n.x + n.y * n.y + n.z * n.z);
    if (!(len > 1e-12) || !is_finite(len)) {
        return rgba;
    }
    let cosv = abs((n.x * d.x + n.y * d.y + n.z * d.z) / len);
    let k = 0.3 + 0.6 * cosv;
    let c2 = cosv * cosv;
    let c4 = c2 * c2;
    let c8 = c4 * c4;
    let c16 = c8 * c8;
    let spec = 0.25 * (c16 * c8) * rgba.w;
    return vec4<f32>(rgba.xyz * k + vec3<f32>(spec), rgba.w);
}

struct Ray {
    acc: vec4<f32>,
    done: bool,
    samples: u32,
    skipped: u32,
    terminated: u32,
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
                continue;
            }
            let q = c + t * md;
            let s = sample_at(vi, cur, q);
            (*ray).samples += 1u;
            k = k + 1;
            if (is_nan(s)) { continue; }
            var rgba = classify(vi, band, s);
            if (rgba.w <= 0.0) { continue; }
            if (SHADING) {
                rgba = shade(vi, cur, q, d, rgba);
            }
            (*ray).acc = blend((*ray).acc, rgba);
            if ((*ray).acc.w >= F.ert) {
                (*ray).done = true;
                (*ray).terminated = 1u;
                return;
            }
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
                if (SHADING) {
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
            if ((*ray).acc.w >= F.ert) {
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
            march_mixed(active_set, curs, mds, d, fa, fb, ray);
        }
    }
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
    return Cursor(0u, -BIG, true, 0u, 1.0, vec3<f32>(0.0));
}

@compute @workgroup_size(8, 8, 1)
fn cast_rays(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    if (lid == 0u) {
        atomicStore(&wg_samples, 0u);
        atomicStore(&wg_skipped, 0u);
        atomicStore(&wg_terminated, 0u);
        atomicStore(&wg_rays, 0u);
    }
    workgroupBarrier();
    var ray = Ray(vec4<f32>(0.0), false, 0u, 0u, 0u);
    let inside = gid.x < F.rect_w && gid.y < F.rect_h;
    if (inside) {
        let x = F.rect_x + gid.x;
        let y = F.rect_y + gid.y;
        let fx = f32(x) + 0.5;
        let fy = f32(y) + 0.5;
        let d0 = F.dir00 + fx * F.du + fy * F.dv;
        let l = sqrt(d0.x * d0.x + d0.y * d0.y + d0.z * d0.z);
        let d = d0 / l;
        let tt = clip_region(F.region_lo, F.region_hi, d);
        if (tt.x < tt.y) {
            if (MULTI) {
                var curs: array<Cursor, 4>;
                var mds: array<vec3<f32>, 4>;
                var spans: array<vec2<f32>, 4>;
                for (var i = 0u; i < F.n_vols; i = i + 1u) {
                    let md = index_dir(i, d);
                    let iv = interval(i, md);
                    mds[i] = md;
                    spans[i] = vec2<f32>(max(iv.x, tt.x), min(iv.y, tt.y));
                    curs[i] = new_cursor();
                }
                march_fragments(&spans, &curs, &mds, d, tt.x, tt.y, &ray);
            } else if (F.n_vols == 1u) {
                let md = index_dir(0u, d);
                let iv = interval(0u, md);
                let a = max(iv.x, tt.x);
                let b = min(iv.y, tt.y);
                if (a < b) {
                    var cur = new_cursor();
                    march_one(0u, &cur, md, d, a, b, &ray);
                }
            }
        }
        out_px[gid.y * F.rect_w + gid.x] = sanitize(ray.acc);
        atomicAdd(&wg_samples, ray.samples);
        atomicAdd(&wg_skipped, ray.skipped);
        atomicAdd(&wg_terminated, ray.terminated);
        atomicAdd(&wg_rays, 1u);
    }
    workgroupBarrier();
    if (lid == 0u) {
        add64(0u, atomicLoad(&wg_samples));
        add64(2u, atomicLoad(&wg_skipped));
        atomicAdd(&stats[4], atomicLoad(&wg_terminated));
        atomicAdd(&stats[5], atomicLoad(&wg_rays));
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
