use super::*;
use kfmap_geometry::imu::ImuSample;

fn scan_header(kind: RequestKind) -> RequestHeader {
    RequestHeader {
        kind: kind as u32,
        ..Default::default()
    }
}

#[test]
fn scan_round_trip_with_every_optional_array() {
    let points = [[1.0f32, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]];
    let views = [[1.0f32, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let covs = [[1.0, 0.1, 0.2, 2.0, 0.3, 3.0]; 3];
    let mut header = scan_header(RequestKind::Cov2Cov);
    let payload = ScanPayload {
        points: &points,
        view_dirs: Some(&views),
        covariances: Some(&covs),
    }
    .encode(&mut header);
    assert_eq!(payload.len(), 36);
    assert_eq!(header.flags, FLAG_VIEW_DIRS | FLAG_COVARIANCES);
    let d = decode_scan(&header, &payload, 10).unwrap();
    assert_eq!(d.points, &points);
    assert_eq!(d.view_dirs.unwrap(), &views);
    let got = d.covariances.unwrap();
    for (g, w) in got.iter().zip(&covs) {
        for (a, b) in g.iter().zip(w) {
            assert!((a - b).abs() < 1e-6);
        }
    }
}

#[test]
fn bad_scans_are_refused_by_name() {
    let points = [[0.0f32; 3]; 4];
    let mut header = scan_header(RequestKind::Nearest);
    let good = ScanPayload {
        points: &points,
        view_dirs: None,
        covariances: None,
    }
    .encode(&mut header);
    assert_eq!(
        decode_scan(&header, &good, 3).unwrap_err().status,
        StatusCode::TooManyPoints
    );
    let mut nan = good.clone();
    nan[7] = f32::NAN;
    let e = decode_scan(&header, &nan, 10).unwrap_err();
    assert_eq!((e.status, e.detail), (StatusCode::NonFinitePoint, 2));
    assert!(e.message.contains("point 2"), "{}", e.message);
    let e = decode_scan(&header, &good[..6], 10).unwrap_err();
    assert_eq!(e.status, StatusCode::BadRequest);
    let empty = RequestHeader {
        point_count: 0,
        ..header
    };
    assert_eq!(
        decode_scan(&empty, &[], 10).unwrap_err().status,
        StatusCode::EmptyScan
    );
    let old = RequestHeader {
        version: PROTOCOL_VERSION + 1,
        ..header
    };
    let e = decode_scan(&old, &good, 10).unwrap_err();
    assert_eq!(e.status, StatusCode::VersionMismatch);
    assert!(e.message.contains("protocol"));
    let flags = RequestHeader {
        flags: 512,
        ..header
    };
    assert_eq!(
        decode_scan(&flags, &good, 10).unwrap_err().status,
        StatusCode::BadRequest
    );
}

#[test]
fn non_finite_view_direction_and_covariance_are_located() {
    let points = [[0.0f32; 3]; 2];
    let views = [[1.0f32, 0.0, 0.0]; 2];
    let covs = [[1.0, 0.0, 0.0, 1.0, 0.0, 1.0]; 2];
    let mut header = scan_header(RequestKind::Cov2Cov);
    let mut payload = ScanPayload {
        points: &points,
        view_dirs: Some(&views),
        covariances: Some(&covs),
    }
    .encode(&mut header);
    payload[6 + 4] = f32::INFINITY;
    let e = decode_scan(&header, &payload, 10).unwrap_err();
    assert!(e.message.starts_with("view direction 1"), "{}", e.message);
    payload[6 + 4] = 0.0;
    payload[12 + 6 + 5] = f32::NAN;
    let e = decode_scan(&header, &payload, 10).unwrap_err();
    assert!(e.message.starts_with("covariance 1"), "{}", e.message);
}

#[test]
fn imu_round_trip_and_refusals() {
    let samples: Vec<ImuSample> = (0..5)
        .map(|i| ImuSample {
            t: 1000.0 + i as f64 * 0.01,
            acc: [0.1, -0.2, 9.8],
            gyro: [0.0, 0.01, 0.0],
        })
        .collect();
    let header = RequestHeader {
        kind: RequestKind::ImuWindow as u32,
        point_count: 5,
        imu_t0: 1000.0,
        ..Default::default()
    };
    let payload = imu_payload(&samples, 1000.0);
    let back = decode_imu(&header, &payload, 100).unwrap();
    for (a, b) in back.iter().zip(&samples) {
        assert!((a.t - b.t).abs() < 1e-6 && (a.acc[2] - b.acc[2]).abs() < 1e-6);
    }
    let mut bad = payload.clone();
    bad[7 * 3 + 2] = f32::NAN;
    assert_eq!(decode_imu(&header, &bad, 100).unwrap_err().detail, 3);
    assert_eq!(
        decode_imu(&header, &payload, 4).unwrap_err().status,
        StatusCode::TooManyPoints
    );
}

#[test]
fn codes_round_trip_and_unknown_codes_are_safe() {
    for kind in RequestKind::ALL {
        assert_eq!(RequestKind::from_code(kind as u32), Some(kind));
    }
    assert_eq!(RequestKind::from_code(99), None);
    assert_eq!(StatusCode::from_code(3), StatusCode::TooManyPoints);
    assert_eq!(StatusCode::from_code(1234), StatusCode::Internal);
    let pose = pose_from_wire(&[1.0, 2.0, 3.0, 0.0, 0.0, 0.6, 0.8]).unwrap();
    assert_eq!(pose_to_wire(&pose), [1.0, 2.0, 3.0, 0.0, 0.0, 0.6, 0.8]);
    assert!(pose_from_wire(&[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0]).is_none());
    assert!(pose_from_wire(&[f64::NAN, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]).is_none());
}

#[test]
fn message_text_is_cut_at_a_character_boundary() {
    let mut h = ResponseHeader::default();
    let long = "é".repeat(MESSAGE_LEN);
    h.set_message(&long);
    assert!(h.message_len as usize <= MESSAGE_LEN && h.message_len % 2 == 0);
    assert!(h.message().chars().all(|c| c == 'é'));
}

/// The offsets documented on the wire types (foreign clients rely on them).
#[test]
fn header_layouts_are_the_documented_ones() {
    use std::mem::{align_of, offset_of, size_of};
    macro_rules! layout {
        ($t:ty, $size:expr, $($f:ident = $at:expr),*) => {
            assert_eq!(size_of::<$t>(), $size, "size of {}", stringify!($t));
            $(assert_eq!(offset_of!($t, $f), $at, "{}::{}", stringify!($t), stringify!($f));)*
        };
    }
    layout!(
        RequestHeader,
        152,
        version = 0,
        kind = 4,
        request_id = 8,
        client_node = 16,
        pose = 32,
        point_count = 88,
        flags = 92,
        k = 96,
        mode = 100,
        radius = 104,
        max_pair_dist = 108,
        max_iterations = 112,
        max_correction = 116,
        keyframe_or_scan_id = 120,
        imu_t0 = 128,
        expected_inlier_ratio = 136,
        keyframes = 140,
        stamp = 144
    );
    layout!(
        WirePairing,
        56,
        query = 0,
        local_index = 4,
        keyframe = 8,
        point = 16,
        dist_sq = 28,
        information = 32
    );
    layout!(
        WirePlace,
        56,
        translation = 0,
        rotation = 24,
        score = 40,
        rank = 48
    );
    assert_eq!(align_of::<WirePlace>(), align_of::<WirePairing>());
    layout!(
        ResponseHeader,
        3416,
        version = 0,
        status = 4,
        request_id = 8,
        detail = 16,
        message_len = 24,
        active_len = 28,
        active = 32,
        server_us = 160,
        pose = 168,
        covariance = 224,
        fitness = 512,
        iterations = 528,
        converged = 532,
        tracking = 536,
        reasons = 540,
        registrations = 544,
        degenerate = 548,
        constraint = 552,
        pose_correction = 568,
        relocalization = 576,
        candidates = 580,
        place_scores = 584,
        tight_fitness = 600,
        has_gravity = 608,
        gravity_members = 612,
        gravity = 616,
        roll_pitch = 640,
        correction = 656,
        gravity_inliers = 688,
        gravity_compensated = 692,
        gravity_pending = 696,
        gravity_skipped = 700,
        bias_observable = 704,
        gravity_reserved = 708,
        gravity_spread_deg = 712,
        accel_bias = 720,
        accel_bias_sigma = 744,
        map_keyframes = 768,
        map_points = 776,
        uptime_s = 784,
        counts = 792,
        p50_us = 888,
        p99_us = 936,
        sessions = 984,
        in_flight = 988,
        map_name_len = 992,
        map_name = 996,
        message = 1060,
        message_reserved = 1300,
        session_gravity = 1304,
        scan_covariance = 3224,
        relocalize_ranking = 3264,
        track = 3312
    );
    layout!(
        WireTrack,
        104,
        predicted = 0,
        t = 56,
        explained = 64,
        slide_loss = 72,
        max_correction = 80,
        hypotheses = 88,
        known = 92,
        imu_refused = 96,
        reserved = 100
    );
    layout!(
        WireRanking,
        48,
        keep_ratio = 0,
        separation_m = 8,
        separation_deg = 16,
        ambiguity_margin = 24,
        distinct_m = 32,
        distinct_deg = 40
    );
    layout!(
        WireCovOptions,
        40,
        k_correspondences = 0,
        min_correspondences = 4,
        center = 8,
        reserved = 12,
        max_distance = 16,
        lambda = 24,
        max_plane_deviation = 32
    );
    layout!(
        WireSessionGravity,
        120,
        client_node = 0,
        members = 16,
        compensated = 20,
        pending = 24,
        skipped = 28,
        inliers = 32,
        has_gravity = 36,
        bias_observable = 40,
        busy = 44,
        roll_pitch = 48,
        spread_deg = 64,
        accel_bias = 72,
        gravity = 96
    );
}

#[test]
fn covariance_options_round_trip_through_a_status_report() {
    use kfmap_geometry::cov::{CovCenter, CovOptions};
    // Every field off its default, so a swapped or dropped field fails.
    let options = CovOptions {
        k_correspondences_for_cov: 12,
        min_correspondences_for_cov: 7,
        max_distance_for_cov: 2.5,
        lambda: -0.01,
        cov_center: CovCenter::Query,
        max_plane_deviation_for_cov: 0.2,
    };
    let wire = WireCovOptions::from(&options);
    assert_eq!(wire.to_options(), Some(options));
    assert_eq!(
        WireCovOptions::from(&CovOptions::default()).to_options(),
        Some(CovOptions::default())
    );
    // An unknown centre code or a value the options refuse gives no options.
    assert_eq!(WireCovOptions { center: 2, ..wire }.to_options(), None);
    assert_eq!(
        WireCovOptions {
            k_correspondences: 1,
            ..wire
        }
        .to_options(),
        None
    );
}

mod remote_frames {
    use super::*;
    use crate::remote::*;

    #[test]
    fn request_frames_carry_the_header_and_payload_bytes_at_their_documented_offsets() {
        let header = RequestHeader {
            kind: RequestKind::Localize as u32,
            request_id: 0x0102_0304_0506_0708,
            point_count: 2,
            stamp: 12.5,
            ..Default::default()
        };
        let payload = [1.0f32, -2.0, 3.5, 4.0, 5.0, 6.0];
        let frame = encode_request(&header, &payload);
        // The layout documented on `RequestHeader`: 152 bytes, request_id at 8, stamp at 144.
        assert_eq!(frame.len(), 152 + 24);
        assert_eq!(frame[8..16], 0x0102_0304_0506_0708u64.to_le_bytes());
        assert_eq!(frame[144..152], 12.5f64.to_le_bytes());
        assert_eq!(frame[152..156], 1.0f32.to_le_bytes());
        // Read back from an unaligned copy.
        let mut shifted = vec![0u8];
        shifted.extend_from_slice(&frame);
        let (h, p) = decode_request(&shifted[1..], 1 << 20).unwrap();
        assert_eq!(h, header);
        assert_eq!(p, payload);
    }

    #[test]
    fn bad_request_frames_are_refused_with_the_reason() {
        let frame = encode_request(&RequestHeader::default(), &[1.0, 2.0]);
        assert!(matches!(
            decode_request(&frame[..100], 1 << 20),
            Err(FrameError::Short {
                len: 100,
                header: 152,
                ..
            })
        ));
        assert!(matches!(
            decode_request(&frame[..frame.len() - 1], 1 << 20),
            Err(FrameError::Ragged { len: 7, .. })
        ));
        assert!(matches!(
            decode_request(&frame, 159),
            Err(FrameError::TooLarge { limit: 159, .. })
        ));
    }

    #[test]
    fn answer_frames_round_trip_and_refuse_partial_pairings() {
        let mut header = ResponseHeader::refusal(9, StatusCode::Busy, "slots");
        header.pose = [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0];
        let pairings = [WirePairing {
            query: 3,
            keyframe: 7,
            point: [1.0, 2.0, 3.0],
            dist_sq: 0.25,
            ..Default::default()
        }; 3];
        let frame = encode_answer(&header, &pairings);
        assert_eq!(frame.len(), answer_frame_len(3));
        assert_eq!(frame.len(), 3416 + 3 * 56);
        let (h, p) = decode_answer(&frame).unwrap();
        assert_eq!(h, header);
        assert_eq!(h.message(), "slots");
        assert_eq!(StatusCode::from_code(h.status), StatusCode::Busy);
        assert_eq!(p, pairings);
        assert!(matches!(
            decode_answer(&frame[..frame.len() - 8]),
            Err(FrameError::Ragged { .. })
        ));
    }

    #[test]
    fn keys_name_map_version_tile_and_client() {
        let v = PROTOCOL_VERSION;
        assert_eq!(
            rpc_key("site", "t3_-2", "robot7"),
            format!("kfmap/site/v{v}/t3_-2/rpc/robot7")
        );
        assert_eq!(
            client_of_rpc_key(&rpc_key("site", "whole", "r1")),
            Some("r1")
        );
        assert_eq!(client_of_rpc_key("kfmap/site/v7/whole/alive"), None);
        assert_eq!(
            tile_of_alive_key("site", &alive_key("site", "t0_0")),
            Some("t0_0")
        );
        assert_eq!(tile_of_alive_key("other", &alive_key("site", "t0_0")), None);
        for bad in ["", "a/b", "a*", "$x", "q?", "#"] {
            assert!(check_key_chunk("map name", bad).is_err(), "{bad:?}");
        }
        assert!(check_key_chunk("map name", "campus-2.v3").is_ok());
    }

    #[test]
    fn failure_replies_read_back_as_their_kind() {
        for f in [
            RemoteFailure::NoServer,
            RemoteFailure::Disconnected,
            RemoteFailure::Timeout,
            RemoteFailure::Gateway,
        ] {
            assert_eq!(
                RemoteFailure::parse(&f.reply("why: because")),
                (f, "why: because")
            );
        }
        assert_eq!(RemoteFailure::parse("garbage").0, RemoteFailure::Gateway);
    }
}

#[test]
fn a_proposed_place_travels_in_a_pairing_slot() {
    let pose = pose_from_wire(&[1234.5, -6789.25, 3.0, 0.0, 0.0, 0.6, 0.8]).unwrap();
    let slot = place_to_wire(&pose, 0.75, 3).to_slot();
    let place = WirePlace::from_slot(slot);
    assert_eq!((place.score, place.rank), (0.75, 3));
    let back = place_from_wire(&place).unwrap();
    // Translation exact (f64); rotation as f32 carries it (< 1e-6 rad).
    assert_eq!(back.translation.vector, pose.translation.vector);
    assert!(back.rotation.angle_to(&pose.rotation) < 1e-6);
    let broken = WirePlace {
        rotation: [0.0, 0.0, 0.0, 2.0],
        ..place
    };
    assert!(place_from_wire(&broken).is_none());
}
