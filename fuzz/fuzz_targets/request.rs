//! Fuzzes the request decoder: a `RequestHeader` with every field arbitrary (kind,
//! version, point_count, flags, k, radius, ...) and an `f32` payload of arbitrary
//! length go through the checks the server applies before any work (`compute` in
//! service/src/server/answer.rs): version, kind, pose, `decode_scan` / `decode_imu` /
//! `decode_stamp`, the cov2cov mode and `localize_params`. Each must answer `Ok` or a
//! `Rejection`, never panic, and allocate nothing proportional to a header field.
//! Also: the wire text helpers and `correspondences_from_wire`.
//! Run: `cargo +nightly fuzz run request`.
#![no_main]

#[path = "common.rs"]
mod common;

use arbitrary::{Arbitrary, Unstructured};
use kfmap_protocol::{
    Cov2CovMode, FLAG_COVARIANCES, FLAG_STAMPED, FLAG_VIEW_DIRS, IMU_SAMPLE_FLOATS, MESSAGE_LEN,
    PROTOCOL_VERSION, RequestHeader, RequestKind, StatusCode, WirePairing, check_version,
    correspondences_from_wire, decode_imu, decode_scan, decode_stamp, pose_from_wire, read_text,
    write_text,
};
use kfmap_service::server::localize_params;
use libfuzzer_sys::fuzz_target;

/// The server's limits (`DEFAULT_MAX_POINTS`, and `MAX_IMU_SAMPLES` of answer.rs).
const MAX_POINTS: usize = 1 << 20;
const MAX_IMU_SAMPLES: usize = 1 << 16;

/// A value the fuzzer may take verbatim or have replaced by one that passes a check,
/// so the checks behind it are reached without guessing e.g. a version and a matching
/// point count at once.
#[derive(Debug, Arbitrary)]
enum Pick<T> {
    Raw(T),
    Valid,
}

#[derive(Debug, Arbitrary)]
struct Input {
    version: Pick<u32>,
    kind: u32,
    request_id: u64,
    client_node: [u64; 2],
    pose: [f64; 7],
    point_count: Pick<u32>,
    flags: u32,
    k: u32,
    mode: u32,
    radius: f32,
    max_pair_dist: f32,
    max_iterations: u32,
    max_correction: f32,
    keyframe_or_scan_id: u64,
    imu_t0: f64,
    expected_inlier_ratio: f32,
    keyframes: u32,
    stamp: f64,
    text: String,
    text_len: u32,
    pairings: Vec<([u32; 2], u64, [f32; 3], f32, [f32; 6])>,
}

fn header_of(input: &Input, payload_len: usize) -> RequestHeader {
    let floats_per_point = |flags: u32| {
        3 + if flags & FLAG_VIEW_DIRS != 0 { 3 } else { 0 }
            + if flags & FLAG_COVARIANCES != 0 { 6 } else { 0 }
    };
    let per = match RequestKind::from_code(input.kind) {
        Some(RequestKind::ImuWindow) => IMU_SAMPLE_FLOATS,
        _ => floats_per_point(input.flags),
    };
    RequestHeader {
        version: match input.version {
            Pick::Raw(v) => v,
            Pick::Valid => PROTOCOL_VERSION,
        },
        kind: input.kind,
        request_id: input.request_id,
        client_node: input.client_node,
        pose: input.pose,
        point_count: match input.point_count {
            Pick::Raw(n) => n,
            Pick::Valid => (payload_len / per) as u32,
        },
        flags: input.flags,
        k: input.k,
        mode: input.mode,
        radius: input.radius,
        max_pair_dist: input.max_pair_dist,
        max_iterations: input.max_iterations,
        max_correction: input.max_correction,
        keyframe_or_scan_id: input.keyframe_or_scan_id,
        imu_t0: input.imu_t0,
        expected_inlier_ratio: input.expected_inlier_ratio,
        keyframes: input.keyframes,
        stamp: input.stamp,
    }
}

fuzz_target!(|data: &[u8]| {
    let mut u = Unstructured::new(data);
    let Ok(input) = Input::arbitrary(&mut u) else {
        return;
    };
    // The rest of the bytes are the payload, as the server's `&[f32]` view of the
    // shared-memory slice: any length, any bit pattern.
    let payload: Vec<f32> = u
        .take_rest()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let header = header_of(&input, payload.len());
    let strict = common::strict();

    // What `compute` does first.
    let version_ok = check_version(&header).is_ok();
    let kind = RequestKind::from_code(header.kind);
    let _ = kind.map(|k| (k.name(), k.carries_scan()));
    let pose = pose_from_wire(&header.pose);
    if strict && let Some(p) = &pose {
        assert!(p.rotation.quaternion().coords.iter().all(|c| c.is_finite()));
    }
    let _ = Cov2CovMode::from_code(header.mode).map(Cov2CovMode::name);
    let _ = localize_params(&header);

    // Every decoder on every header, whatever its kind: none may panic.
    let stamp = decode_stamp(&header);
    if strict {
        match &stamp {
            Ok(Some(t)) => assert!(t.is_finite() && header.flags & FLAG_STAMPED != 0),
            Ok(None) => assert_eq!(header.flags & FLAG_STAMPED, 0),
            Err(r) => assert_eq!(r.status, StatusCode::BadRequest),
        }
    }
    for max in [MAX_POINTS, 1, 0, usize::MAX] {
        match decode_scan(&header, &payload, max) {
            Ok(scan) => {
                if strict {
                    let n = header.point_count as usize;
                    assert!(version_ok && n >= 1 && n <= max);
                    assert_eq!(scan.points.len(), n);
                    assert_eq!(
                        scan.view_dirs.map(<[_]>::len),
                        (header.flags & FLAG_VIEW_DIRS != 0).then_some(n)
                    );
                    assert_eq!(
                        scan.covariances.map(<[_]>::len),
                        (header.flags & FLAG_COVARIANCES != 0).then_some(n)
                    );
                    assert!(scan.points.as_flattened().iter().all(|v| v.is_finite()));
                    assert!(
                        scan.view_dirs
                            .unwrap_or(&[])
                            .as_flattened()
                            .iter()
                            .all(|v| v.is_finite())
                    );
                    assert!(
                        scan.covariances
                            .unwrap_or(&[])
                            .as_flattened()
                            .iter()
                            .all(|v| v.is_finite())
                    );
                }
            }
            Err(r) => {
                let _ = format!("{r:?}");
            }
        }
        match decode_imu(&header, &payload, max.min(MAX_IMU_SAMPLES)) {
            Ok(samples) => {
                if strict {
                    let n = header.point_count as usize;
                    assert!(version_ok && n >= 1 && n <= max.min(MAX_IMU_SAMPLES));
                    assert_eq!(samples.len(), n);
                    for s in &samples {
                        assert!(s.t.is_finite());
                        assert!(s.acc.iter().chain(&s.gyro).all(|v| v.is_finite()));
                    }
                }
            }
            Err(r) => {
                let _ = format!("{r:?}");
            }
        }
    }

    // Wire text: a message cut to the buffer at a character boundary reads back as a
    // prefix; any length read from a foreign header is clamped.
    let mut buffer = [0u8; MESSAGE_LEN];
    let used = write_text(&mut buffer, &input.text);
    let back = read_text(&buffer, used);
    if strict {
        assert!(used as usize <= MESSAGE_LEN);
        assert!(input.text.starts_with(&back));
    }
    let _ = read_text(&buffer, input.text_len);

    // Cov2cov answers: pairings naming points outside the scan are skipped.
    if let Ok(scan) = decode_scan(&header, &payload, MAX_POINTS) {
        let pairings: Vec<WirePairing> = input
            .pairings
            .iter()
            .map(
                |&([query, local_index], keyframe, point, dist_sq, information)| WirePairing {
                    query,
                    local_index,
                    keyframe,
                    point,
                    dist_sq,
                    information,
                },
            )
            .collect();
        let found = correspondences_from_wire(&pairings, scan.points);
        if strict {
            let inside = pairings
                .iter()
                .filter(|p| (p.query as usize) < scan.points.len())
                .count();
            assert_eq!(found.len(), inside);
        }
    }
});
