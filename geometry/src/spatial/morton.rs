//! Morton (Z-order) sorting of query points.

/// Spreads the low 21 bits of `v` to every third bit (bit i -> bit 3i).
fn spread_bits(v: u64) -> u64 {
    let mut x = v & 0x1f_ffff;
    x = (x | (x << 32)) & 0x001f_0000_0000_ffff;
    x = (x | (x << 16)) & 0x001f_0000_ff00_00ff;
    x = (x | (x << 8)) & 0x100f_00f0_0f00_f00f;
    x = (x | (x << 4)) & 0x10c3_0c30_c30c_30c3;
    x = (x | (x << 2)) & 0x1249_2492_4924_9249;
    x
}

/// Indices of `points` along a Morton (Z-order) curve over their bounding box:
/// queries in this order reuse the tree nodes the previous query touched.
/// Non-finite points go last, in input order.
pub fn morton_order(points: &[[f32; 3]]) -> Vec<u32> {
    let finite = |p: &[f32; 3]| p.iter().all(|c| c.is_finite());
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in points.iter().filter(|p| finite(p)) {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let cells = f64::from((1u32 << 21) - 1);
    let scale: [f64; 3] =
        std::array::from_fn(|a| cells / f64::from(hi[a] - lo[a]).max(f64::MIN_POSITIVE));
    let mut keyed: Vec<(u64, u32)> = points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let key = if finite(p) {
                (0..3).fold(0, |key, a| {
                    let cell = (f64::from(p[a] - lo[a]) * scale[a]) as u64;
                    key | (spread_bits(cell) << a)
                })
            } else {
                u64::MAX
            };
            (key, i as u32)
        })
        .collect();
    keyed.sort_unstable();
    keyed.into_iter().map(|(_, i)| i).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn morton_order_is_a_permutation_along_the_z_curve() {
        // A 4 x 4 x 4 grid: the Z curve visits the 2 x 2 x 2 octant blocks one by one,
        // x fastest, then y, then z (closed form: key = interleave(z, y, x)).
        let mut points = Vec::new();
        for z in 0..4 {
            for y in 0..4 {
                for x in 0..4 {
                    points.push([x as f32, y as f32, z as f32]);
                }
            }
        }
        points.reverse();
        points.push([f32::NAN, 0.0, 0.0]);
        let order = morton_order(&points);
        let mut seen = order.clone();
        seen.sort_unstable();
        assert_eq!(seen, (0..points.len() as u32).collect::<Vec<_>>());
        assert_eq!(*order.last().unwrap(), 64, "non-finite point last");
        let key = |p: &[f32; 3]| {
            let bits = |v: f32, shift: u32| {
                (0..2)
                    .map(|b| (((v as u32) >> b) & 1) << (3 * b + shift))
                    .sum::<u32>()
            };
            bits(p[0], 0) + bits(p[1], 1) + bits(p[2], 2)
        };
        let keys: Vec<u32> = order[..64]
            .iter()
            .map(|&i| key(&points[i as usize]))
            .collect();
        assert_eq!(keys, (0..64).collect::<Vec<_>>());
    }
}
