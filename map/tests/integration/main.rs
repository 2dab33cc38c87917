//! The integration tests of this crate, as one binary (one link instead of one per
//! file: each release test binary is a thin-LTO link of every dependency).

mod large_map;
