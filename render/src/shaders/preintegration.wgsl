// Length-free pre-integration (segment_integral.rs), binding 10: prefix integrals of
// extinction and emission over the TF table's bins, rows prefix hi / prefix lo / point values κ, κ·c (see the Rust doc
// for why the hi/lo split). 1×3 when unused.

@group(0) @binding(10) var preintegration_table: texture_2d<f32>;

fn integral_texel(i: i32, row: i32) -> vec4<f32> {
    return textureLoad(preintegration_table, vec2<i32>(i, row), 0);
}

// Cell of position x (entry spacings): −1 below the table, n−1 above it.
fn integral_cell(x: f32, n: i32) -> i32 {
    return clamp(i32(floor(x)), -1, n - 1);
}

// κ and κ·c at x: linear between entries, constant beyond the ends.
fn integral_point(x: f32, cell: i32, n: i32) -> vec4<f32> {
    if cell < 0 {
        return integral_texel(0, 2);
    }
    if cell >= n - 1 {
        return integral_texel(n - 1, 2);
    }
    return mix(integral_texel(cell, 2), integral_texel(cell + 1, 2), x - f32(cell));
}

// The part of the prefix at x beyond its entry's hi word (lo word plus the partial cell).
fn integral_rest(x: f32, cell: i32, n: i32) -> vec4<f32> {
    if cell < 0 {
        return integral_texel(0, 1) + x * integral_texel(0, 2);
    }
    if cell >= n - 1 {
        return integral_texel(n - 1, 1) + (x - f32(n - 1)) * integral_texel(n - 1, 2);
    }
    let f = x - f32(cell);
    let p = integral_texel(cell, 2);
    let q = integral_texel(cell + 1, 2);
    return integral_texel(cell, 1) + f * p + 0.5 * f * f * (q - p);
}

// Premultiplied colour and opacity of a segment of `length` mm whose value runs linearly
// from `front` to `back` (physical units): the twin of SegmentIntegralTable::segment.
fn preintegrated_segment(front: f32, back: f32, length: f32) -> vec4<f32> {
    let n = i32(textureDimensions(preintegration_table).x);
    let xf = (front - P.value_map.z) * P.value_map.w;
    let xb = (back - P.value_map.z) * P.value_map.w;
    let cf = integral_cell(xf, n);
    let cb = integral_cell(xb, n);
    let dx = xb - xf;
    var mean: vec4<f32>;
    if cf == cb || abs(dx) < 1e-3 {
        let xm = 0.5 * (xf + xb);
        mean = integral_point(xm, integral_cell(xm, n), n);
    } else {
        let hf = integral_texel(clamp(cf, 0, n - 1), 0);
        let hb = integral_texel(clamp(cb, 0, n - 1), 0);
        mean = ((hb - hf) + (integral_rest(xb, cb, n) - integral_rest(xf, cf, n))) / dx;
    }
    let kappa = max(mean.x, 0.0);
    let alpha = 1.0 - exp(-kappa * max(length, 0.0));
    if kappa <= 0.0 || alpha <= 0.0 {
        return vec4<f32>(0.0);
    }
    let colour = clamp(mean.yzw / kappa, vec3<f32>(0.0), vec3<f32>(1.0)) * alpha;
    return vec4<f32>(colour, alpha);
}

// Extinction per mm at one value: > 0 where the TF is not transparent.
fn extinction_at(v: f32) -> f32 {
    let n = i32(textureDimensions(preintegration_table).x);
    let x = (v - P.value_map.z) * P.value_map.w;
    return integral_point(x, integral_cell(x, n), n).x;
}
