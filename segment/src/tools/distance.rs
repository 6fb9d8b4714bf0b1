//! Exact Euclidean distance transforms with anisotropic spacing (Felzenszwalb & Huttenlocher,
//! "Distance transforms of sampled functions", 2012): squared distances are separable, so one
//! lower envelope of parabolas per line and axis, with voxel positions in mm.

/// Stands for "no feature on this line yet": large, yet finite so envelope arithmetic stays
/// free of inf − inf.
pub(crate) const FAR: f64 = 1e30;

/// In place: `f[q] ← min_p f[p] + ((q − p)·spacing)²` along one line.
fn envelope_1d(
    f: &mut [f64],
    spacing_mm: f64,
    v: &mut Vec<usize>,
    z: &mut Vec<f64>,
    d: &mut Vec<f64>,
) {
    let n = f.len();
    if n <= 1 {
        return;
    }
    v.clear();
    z.clear();
    d.clear();
    d.extend_from_slice(f);
    let x = |q: usize| q as f64 * spacing_mm;
    let intersection = |d: &[f64], q: usize, p: usize| {
        ((d[q] + x(q) * x(q)) - (d[p] + x(p) * x(p))) / (2.0 * (x(q) - x(p)))
    };
    v.push(0);
    z.push(f64::NEG_INFINITY);
    for q in 1..n {
        loop {
            let p = v[v.len() - 1];
            let s = intersection(d, q, p);
            if s <= z[z.len() - 1] && v.len() > 1 {
                v.pop();
                z.pop();
                continue;
            }
            if s <= z[z.len() - 1] {
                // The first parabola is beaten everywhere: replace it.
                v[0] = q;
                break;
            }
            v.push(q);
            z.push(s);
            break;
        }
    }
    let mut k = 0;
    for (q, out) in f.iter_mut().enumerate() {
        while k + 1 < v.len() && z[k + 1] < x(q) {
            k += 1;
        }
        let p = v[k];
        let dx = x(q) - x(p);
        *out = (dx * dx + d[p]).min(FAR);
    }
}

/// Squared distance (mm²) from every voxel centre of a box (`dims`, i fastest) to the nearest
/// feature voxel (`FAR` where there is none).
pub(crate) fn squared_distance(
    dims: [usize; 3],
    spacing_mm: [f64; 3],
    feature: &[bool],
) -> Vec<f64> {
    let mut f: Vec<f64> = feature.iter().map(|&x| if x { 0.0 } else { FAR }).collect();
    let (mut v, mut z, mut d) = (Vec::new(), Vec::new(), Vec::new());
    let [nx, ny, nz] = dims;
    let mut line = Vec::new();
    for (axis, &spacing) in spacing_mm.iter().enumerate() {
        let (len, stride) = match axis {
            0 => (nx, 1),
            1 => (ny, nx),
            _ => (nz, nx * ny),
        };
        if len <= 1 {
            continue;
        }
        for start in 0..nx * ny * nz {
            // A line starts where the coordinate along `axis` is 0.
            let coord = (start / stride) % len;
            if coord != 0 {
                continue;
            }
            line.clear();
            line.extend((0..len).map(|q| f[start + q * stride]));
            envelope_1d(&mut line, spacing, &mut v, &mut z, &mut d);
            for (q, &value) in line.iter().enumerate() {
                f[start + q * stride] = value;
            }
        }
    }
    f
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_transform_equals_brute_force_with_anisotropic_spacing() {
        let dims = [13usize, 9, 7];
        let spacing = [0.7, 1.3, 2.1];
        let n = dims.iter().product::<usize>();
        let feature: Vec<bool> = (0..n).map(|x| (x * 37 + 11) % 53 == 0).collect();
        assert!(feature.iter().filter(|&&f| f).count() > 3);
        let got = squared_distance(dims, spacing, &feature);
        let at = |x: usize| [x % 13, (x / 13) % 9, x / 117];
        for (q, &got_q) in got.iter().enumerate() {
            let want = (0..n)
                .filter(|&p| feature[p])
                .map(|p| {
                    let (a, b) = (at(q), at(p));
                    (0..3)
                        .map(|ax| ((a[ax] as f64 - b[ax] as f64) * spacing[ax]).powi(2))
                        .sum::<f64>()
                })
                .fold(f64::INFINITY, f64::min);
            assert!(
                (got_q - want).abs() < 1e-9,
                "voxel {:?}: {} vs {}",
                at(q),
                got_q,
                want
            );
        }
        assert!(squared_distance([4, 1, 1], [1.0; 3], &[false; 4])
            .iter()
            .all(|&d| d >= FAR));
    }
}
