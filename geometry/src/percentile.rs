//! Percentiles of samples, one definition for every figure kfmap prints or asserts
//! (server request latencies, localization and benchmark timings, plot colour and view
//! ranges): the nearest rank.
//!
//! The `q`-percentile of `n` sorted values is the value of rank `ceil(q n)` (1-based,
//! at least 1): the smallest value with at least a fraction `q` of the values at or
//! below it. It is always one of the values, never an interpolation between two.
//!
//! With few samples a high percentile is the maximum: the p99 of fewer than 100
//! samples is the largest of them (a p99 over 61 samples is the maximum), and
//! [`is_maximum`] says so, so that the figure can be labelled where it is printed.

/// How far above an integer `q n` may land from floating-point rounding alone and still
/// count as that integer (`0.07 * 100.0` is `7.000000000000001`, whose rank is 7).
const ROUNDING: f64 = 1e-9;

/// The 1-based rank of the `q`-percentile (`q` in 0..=1, clamped) among `n` values:
/// `ceil(q n)`, at least 1 and at most `n`. Zero only when `n` is zero.
pub fn rank(n: usize, q: f64) -> usize {
    if n == 0 {
        return 0;
    }
    let exact = q.clamp(0.0, 1.0) * n as f64;
    ((exact - ROUNDING).ceil() as usize).clamp(1, n)
}

/// Nearest-rank `q`-percentile (`q` in 0..=1) of `sorted` (ascending): the value of
/// rank [`rank`]`(n, q)`. `T::default()` (zero) when `sorted` is empty.
pub fn percentile<T: Copy + Default>(sorted: &[T], q: f64) -> T {
    match rank(sorted.len(), q) {
        0 => T::default(),
        r => sorted[r - 1],
    }
}

/// True when the `q`-percentile of `n` samples is their maximum (for p99: `n` < 100),
/// so a printed figure should say it is the largest sample, not a tail estimate.
pub fn is_maximum(n: usize, q: f64) -> bool {
    n > 0 && rank(n, q) == n
}

/// How to name a printed p99 of `samples` values: "p99", or "p99 (= max of N)" when
/// there are too few (under 100) for the nearest-rank 99th percentile to be anything
/// but their maximum.
pub fn p99_label(samples: usize) -> String {
    if is_maximum(samples, 0.99) {
        format!("p99 (= max of {samples})")
    } else {
        "p99".to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Brute force of the definition in exact integer arithmetic, for `q` = `percent`
    /// / 100: the smallest value with at least `percent` % of the values at or below
    /// it (the first one for 0 %).
    fn oracle(values: &[u32], percent: usize) -> u32 {
        let n = values.len();
        *values
            .iter()
            .find(|&&v| {
                let at_or_below = values.iter().filter(|&&x| x <= v).count();
                at_or_below * 100 >= percent * n
            })
            .unwrap()
    }

    #[test]
    fn nearest_rank_matches_the_brute_force_definition() {
        for n in 1..=250usize {
            // Distinct sorted values, not their ranks.
            let values: Vec<u32> = (0..n as u32).map(|i| 3 * i + 1).collect();
            for percent in 0..=100 {
                let q = percent as f64 / 100.0;
                assert_eq!(
                    percentile(&values, q),
                    oracle(&values, percent),
                    "n {n}, {percent} %"
                );
                // Closed form: rank ceil(percent n / 100), at least 1.
                assert_eq!(
                    rank(n, q),
                    (percent * n).div_ceil(100).max(1),
                    "n {n}, {percent} %"
                );
            }
        }
    }

    #[test]
    fn few_samples_make_the_p99_the_maximum() {
        let v: Vec<f32> = (1..=100).map(|x| x as f32).collect();
        assert_eq!(percentile(&v, 0.5), 50.0);
        assert_eq!(percentile(&v, 0.99), 99.0);
        assert!(!is_maximum(100, 0.99));
        for n in 1..100 {
            assert!(is_maximum(n, 0.99), "{n}");
            assert_eq!(percentile(&v[..n], 0.99), n as f32);
        }
        assert!(is_maximum(61, 0.99) && !is_maximum(61, 0.5));
        assert!(!is_maximum(0, 0.99));
        assert_eq!(percentile::<f64>(&[], 0.5), 0.0);
        assert_eq!(percentile(&[4.0], 0.0), 4.0);
        // Out-of-range q is clamped.
        assert_eq!(percentile(&v, 1.5), 100.0);
        assert_eq!(percentile(&v, -1.0), 1.0);
        // The printed label says so.
        assert_eq!(p99_label(61), "p99 (= max of 61)");
        assert_eq!(p99_label(99), "p99 (= max of 99)");
        assert_eq!(p99_label(100), "p99");
    }
}
