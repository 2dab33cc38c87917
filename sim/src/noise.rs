//! Seeded random draws for the simulator: one independent stream per scan or sensor,
//! so scans can be generated in parallel and still be byte-identical run to run.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// A stream for `(seed, stream)`: different streams are independent.
pub fn stream(seed: u64, stream: u64) -> StdRng {
    // SplitMix64 finalizer: well-spread seeds for neighbouring stream numbers.
    let mut z = seed ^ stream.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    StdRng::seed_from_u64(z ^ (z >> 31))
}

/// A standard normal draw (Box-Muller).
pub fn gaussian(rng: &mut StdRng) -> f64 {
    let u1: f64 = rng.random::<f64>().max(f64::MIN_POSITIVE);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}
