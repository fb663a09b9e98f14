struct Globals {
    view_proj: mat4x4<f32>,
    sun: vec4<f32>,
    params: vec4<f32>,
    eye: vec4<f32>,
    atmos: vec4<f32>,
};
struct BlockU {
    offset: vec4<f32>,
    offset_lo: vec4<f32>,
    tex: vec4<f32>,
    flags: vec4<f32>,
};
@group(0) @binding(0) var<uniform> g: Globals;
@group(1) @binding(0) var<uniform> b: BlockU;
@group(2) @binding(0) var tex: texture_2d<f32>;
@group(2) @binding(1) var samp: sampler;

struct VOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) normal: vec3<f32>,
    @location(1) uv: vec2<f32>,
    @location(2) alt: f32,
    @location(3) rel: vec3<f32>,
};

@vertex
fn vs(
    @location(0) pos: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) uv: vec2<f32>,
    @location(3) alt: f32,
    @location(4) pos_lo: vec4<f32>,
) -> VOut {
    var out: VOut;
    // Camera-relative: the block centre minus the eye was computed in f64 and
    // split in two f32 parts; one rounding (camera_relative.wgsl).
    // offset.w is 0.0, whose bits are the opaque zero camera_relative needs.
    let rel = camera_relative(pos, pos_lo.xyz, b.offset.xyz, b.offset_lo.xyz, bitcast<u32>(b.offset.w));
    out.clip = g.view_proj * vec4<f32>(rel, 1.0);
    out.normal = normal;
    out.uv = uv;
    out.alt = alt;
    out.rel = rel;
    return out;
}

// deep blue -> blue -> green -> brown -> white
fn ramp(a: f32) -> vec3<f32> {
    let deep = vec3<f32>(0.0, 0.02, 0.15);
    let shallow = vec3<f32>(0.05, 0.25, 0.6);
    let green = vec3<f32>(0.1, 0.45, 0.12);
    let brown = vec3<f32>(0.4, 0.28, 0.12);
    let white = vec3<f32>(0.95, 0.95, 0.95);
    if (a < 0.0) {
        return mix(shallow, deep, clamp(-a / 6000.0, 0.0, 1.0));
    }
    if (a < 1500.0) {
        return mix(green, brown, a / 1500.0);
    }
    return mix(brown, white, clamp((a - 1500.0) / 3500.0, 0.0, 1.0));
}

// Aerial perspective (render/settings.rs `Atmosphere`): optical depth rho(h) L / V
// with L the distance, at most the air column H / cos(zenith) at the point.
fn aerial(c: vec3<f32>, rel: vec3<f32>, alt: f32) -> vec3<f32> {
    if (g.atmos.z < 0.5) {
        return c;
    }
    let dist = length(rel);
    if (!(dist > 0.0)) {
        return c;
    }
    // The point's up: eye + rel in f32 loses metres far out, not direction.
    let up = normalize(g.eye.xyz + rel);
    let cos_z = max(dot(-rel / dist, up), 0.02);
    let h = clamp(alt, 0.0, 1.0e5);
    let path = min(dist, g.atmos.x / cos_z);
    let tau = exp(-h / g.atmos.x) * path / g.atmos.y;
    let haze = 1.0 - exp(-tau);
    let sun_up = clamp(dot(up, g.sun.xyz), 0.0, 1.0);
    // The sky's colour: render/settings.rs `Atmosphere::sky_colour`, which also
    // clears the background inside the air (keep the two equal).
    let sky = vec3<f32>(0.50, 0.66, 0.90) * (0.2 + 0.8 * sun_up);
    return mix(c, sky, haze);
}

// Where the colour texture is coarser than the mesh (`coarse` octaves of
// mesh samples per texel): rock on steep slopes and snow on high flat
// ground, blended in as the texture gets coarser, so that 10 m relief under
// a 1 km texel does not look like a smooth texture.
fn detail(c: vec3<f32>, n: vec3<f32>, rel: vec3<f32>, alt: f32, coarse: f32) -> vec3<f32> {
    let k = clamp((coarse - 1.0) / 3.0, 0.0, 1.0);
    if (k <= 0.0) {
        return c;
    }
    let up = normalize(g.eye.xyz + rel);
    let flat = clamp(dot(n, up), 0.0, 1.0);
    let rock = vec3<f32>(0.32, 0.29, 0.26);
    let steep = smoothstep(0.9, 0.7, flat);
    var out = mix(c, rock, steep * 0.8);
    let snow = smoothstep(3500.0, 4500.0, alt) * smoothstep(0.75, 0.9, flat);
    out = mix(out, vec3<f32>(0.92, 0.93, 0.95), snow);
    return mix(c, out, k);
}

@fragment
fn fs(in: VOut) -> @location(0) vec4<f32> {
    let t = textureSample(tex, samp, in.uv * b.tex.xy + b.tex.zw).rgb;
    let n = normalize(in.normal);
    let base = select(ramp(in.alt), detail(t, n, in.rel, in.alt, b.flags.y), b.flags.x > 0.5);
    let diffuse = max(dot(n, g.sun.xyz), 0.0);
    let lit = base * (g.params.x + (1.0 - g.params.x) * diffuse);
    return vec4<f32>(aerial(lit, in.rel, in.alt), 1.0);
}
