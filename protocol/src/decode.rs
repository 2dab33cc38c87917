//! The payload layout: encoding on the client, checking and decoding on the server.
//! Nothing here trusts the header; every length and value is checked.

use std::mem::MaybeUninit;

use super::wire::{
    FLAG_COVARIANCES, FLAG_FINISH_CHOSEN, FLAG_LEVELLED, FLAG_PLACES_ONLY, FLAG_SCORE_CHOSEN,
    FLAG_STAMPED, FLAG_TRACK_FROM_POSE, FLAG_TRACK_RESET, FLAG_VIEW_DIRS, RequestHeader,
    WirePairing,
};
use super::{IMU_SAMPLE_FLOATS, PROTOCOL_VERSION, StatusCode};
use kfmap_geometry::geometry::{PackedSym3, to_vec3, unpack_sym3};
use kfmap_geometry::imu::ImuSample;
use kfmap_geometry::registration::Correspondence;
use kfmap_map::map::Pairing;

/// Why a request was refused: the status, a message naming the problem, a detail value.
#[derive(Debug, Clone, PartialEq)]
pub struct Rejection {
    /// Status code sent back.
    pub status: StatusCode,
    /// What is wrong, for the client's error message.
    pub message: String,
    /// E.g. the index of the first bad point.
    pub detail: u64,
}

impl Rejection {
    /// A rejection without detail.
    pub fn new(status: StatusCode, message: impl Into<String>) -> Self {
        Self {
            status,
            message: message.into(),
            detail: 0,
        }
    }
}

/// A scan to send: points in the sensor frame, optional unit view directions and
/// optional packed covariances (m^2), one per point.
#[derive(Debug, Clone, Copy)]
pub struct ScanPayload<'a> {
    /// Points, sensor frame, metres.
    pub points: &'a [[f32; 3]],
    /// View directions (sensor to point, unit), sensor frame.
    pub view_dirs: Option<&'a [[f32; 3]]>,
    /// Packed covariances (xx xy xz yy yz zz), sensor frame, m^2.
    pub covariances: Option<&'a [PackedSym3]>,
}

impl ScanPayload<'_> {
    /// Floats the payload takes (each array by its own length).
    pub fn float_len(&self) -> usize {
        3 * self.points.len()
            + self.view_dirs.map_or(0, |v| 3 * v.len())
            + self.covariances.map_or(0, |c| 6 * c.len())
    }

    /// A message when the optional arrays do not have one entry per point.
    pub fn check_lengths(&self) -> Result<(), String> {
        let n = self.points.len();
        let mismatch = |what: &str, len: usize| {
            (len != n).then(|| format!("{len} {what} for {n} points; give one per point"))
        };
        match (
            self.view_dirs
                .and_then(|v| mismatch("view directions", v.len())),
            self.covariances
                .and_then(|c| mismatch("covariances", c.len())),
        ) {
            (Some(m), _) | (None, Some(m)) => Err(m),
            (None, None) => Ok(()),
        }
    }

    /// Sets the header's count and flags, and writes exactly [`Self::float_len`] floats
    /// to the front of `out`, e.g. a loaned shared-memory slice; returns how many it
    /// wrote, counted as it writes them (callers check it before `assume_init`).
    pub fn write(&self, header: &mut RequestHeader, out: &mut [MaybeUninit<f32>]) -> usize {
        header.point_count = self.points.len() as u32;
        // The payload's own flags are set here; the request's others are the caller's.
        header.flags &= FLAG_STAMPED
            | FLAG_LEVELLED
            | FLAG_PLACES_ONLY
            | FLAG_SCORE_CHOSEN
            | FLAG_FINISH_CHOSEN;
        let mut at = 0;
        let mut put = |values: &[f32]| {
            for (dst, &v) in out[at..at + values.len()].iter_mut().zip(values) {
                dst.write(v);
            }
            at += values.len();
        };
        put(self.points.as_flattened());
        if let Some(v) = self.view_dirs {
            header.flags |= FLAG_VIEW_DIRS;
            put(v.as_flattened());
        }
        if let Some(c) = self.covariances {
            header.flags |= FLAG_COVARIANCES;
            put(c.as_flattened());
        }
        at
    }

    /// [`Self::write`] into a new vector.
    pub fn encode(&self, header: &mut RequestHeader) -> Vec<f32> {
        let mut out = vec![MaybeUninit::uninit(); self.float_len()];
        let written = self.write(header, &mut out);
        assert_eq!(written, out.len(), "write covers the whole payload");
        out.into_iter()
            // SAFETY: `write` wrote the first `written` elements, one by one, and the
            // assertion above checked that this is every element of `out`.
            .map(|v| unsafe { v.assume_init() })
            .collect()
    }
}

/// A checked scan request, borrowing the payload.
#[derive(Debug, Clone)]
pub struct DecodedScan<'a> {
    /// Points, sensor frame.
    pub points: &'a [[f32; 3]],
    /// View directions, when sent.
    pub view_dirs: Option<&'a [[f32; 3]]>,
    /// Packed covariances, when sent.
    pub covariances: Option<&'a [PackedSym3]>,
}

/// Checks the protocol version.
pub fn check_version(header: &RequestHeader) -> Result<(), Rejection> {
    if header.version != PROTOCOL_VERSION {
        return Err(Rejection::new(
            StatusCode::VersionMismatch,
            format!(
                "client speaks kfmap protocol {} but this server speaks {PROTOCOL_VERSION}; use a client and server of the same release",
                header.version
            ),
        ));
    }
    Ok(())
}

/// Checks and decodes a scan payload: version, counts against the payload length and
/// `max_points`, and every value finite.
pub fn decode_scan<'a>(
    header: &RequestHeader,
    payload: &'a [f32],
    max_points: usize,
) -> Result<DecodedScan<'a>, Rejection> {
    check_version(header)?;
    let n = header.point_count as usize;
    if n == 0 {
        return Err(Rejection::new(
            StatusCode::EmptyScan,
            "the scan has no points",
        ));
    }
    if n > max_points {
        return Err(Rejection {
            status: StatusCode::TooManyPoints,
            message: format!(
                "the scan has {n} points; this server takes at most {max_points} per request (server.toml: max-points-per-request)"
            ),
            detail: n as u64,
        });
    }
    let known = FLAG_VIEW_DIRS
        | FLAG_COVARIANCES
        | FLAG_STAMPED
        | FLAG_LEVELLED
        | FLAG_PLACES_ONLY
        | FLAG_SCORE_CHOSEN
        | FLAG_FINISH_CHOSEN
        | FLAG_TRACK_RESET
        | FLAG_TRACK_FROM_POSE;
    if header.flags & !known != 0 {
        return Err(Rejection::new(
            StatusCode::BadRequest,
            format!("unknown flag bits {:#x}", header.flags),
        ));
    }
    let with_views = header.flags & FLAG_VIEW_DIRS != 0;
    let with_covs = header.flags & FLAG_COVARIANCES != 0;
    let expected = 3 * n + if with_views { 3 * n } else { 0 } + if with_covs { 6 * n } else { 0 };
    if payload.len() != expected {
        return Err(Rejection::new(
            StatusCode::BadRequest,
            format!(
                "payload holds {} floats but {n} points with these flags need {expected}",
                payload.len()
            ),
        ));
    }
    if let Some(bad) = payload.iter().position(|v| !v.is_finite()) {
        let views_end = 3 * n + if with_views { 3 * n } else { 0 };
        let (what, index) = if bad < 3 * n {
            ("point", bad / 3)
        } else if bad < views_end {
            ("view direction", (bad - 3 * n) / 3)
        } else {
            ("covariance", (bad - views_end) / 6)
        };
        return Err(Rejection {
            status: StatusCode::NonFinitePoint,
            message: format!("{what} {index} is not finite (NaN or infinite)"),
            detail: index as u64,
        });
    }
    let (points, rest) = payload.split_at(3 * n);
    let (views, covs) = rest.split_at(if with_views { 3 * n } else { 0 });
    Ok(DecodedScan {
        points: points.as_chunks::<3>().0,
        view_dirs: with_views.then_some(views.as_chunks::<3>().0),
        covariances: with_covs.then_some(covs.as_chunks::<6>().0),
    })
}

/// The time of the request's pose when it carries one (`FLAG_STAMPED`); a stamp that
/// is not a finite number of seconds is refused.
pub fn decode_stamp(header: &RequestHeader) -> Result<Option<f64>, Rejection> {
    if header.flags & FLAG_STAMPED == 0 {
        return Ok(None);
    }
    if !header.stamp.is_finite() {
        return Err(Rejection::new(
            StatusCode::BadRequest,
            format!("the pose's stamp is {} s; give a finite time", header.stamp),
        ));
    }
    Ok(Some(header.stamp))
}

/// The `ImuWindow` payload of `samples`, times relative to `t0`.
pub fn imu_payload(samples: &[ImuSample], t0: f64) -> Vec<f32> {
    samples
        .iter()
        .flat_map(|s| {
            let a = s.acc.map(|x| x as f32);
            let g = s.gyro.map(|x| x as f32);
            [(s.t - t0) as f32, a[0], a[1], a[2], g[0], g[1], g[2]]
        })
        .collect()
}

/// Checks and decodes an `ImuWindow` payload into samples (absolute times).
pub fn decode_imu(
    header: &RequestHeader,
    payload: &[f32],
    max_samples: usize,
) -> Result<Vec<ImuSample>, Rejection> {
    check_version(header)?;
    let n = header.point_count as usize;
    if n == 0 {
        return Err(Rejection::new(
            StatusCode::EmptyScan,
            "the IMU window has no samples",
        ));
    }
    if n > max_samples {
        return Err(Rejection {
            status: StatusCode::TooManyPoints,
            message: format!("the IMU window has {n} samples; at most {max_samples} are taken"),
            detail: n as u64,
        });
    }
    if payload.len() != n * IMU_SAMPLE_FLOATS || !header.imu_t0.is_finite() {
        return Err(Rejection::new(
            StatusCode::BadRequest,
            format!(
                "IMU payload holds {} floats but {n} samples need {} (and imu_t0 must be finite)",
                payload.len(),
                n * IMU_SAMPLE_FLOATS
            ),
        ));
    }
    if let Some(bad) = payload.iter().position(|v| !v.is_finite()) {
        let sample = bad / IMU_SAMPLE_FLOATS;
        return Err(Rejection {
            status: StatusCode::NonFinitePoint,
            message: format!("IMU sample {sample} is not finite (NaN or infinite)"),
            detail: sample as u64,
        });
    }
    Ok(payload
        .as_chunks::<IMU_SAMPLE_FLOATS>()
        .0
        .iter()
        .map(|v| ImuSample {
            t: header.imu_t0 + v[0] as f64,
            acc: [v[1] as f64, v[2] as f64, v[3] as f64],
            gyro: [v[4] as f64, v[5] as f64, v[6] as f64],
        })
        .collect())
}

/// The pairings of a cov2cov answer as solver correspondences: source = the scan point
/// (sensor frame), target = the map point (map frame). Pairings naming a point outside
/// the scan are skipped.
pub fn correspondences_from_wire(
    pairings: &[WirePairing],
    scan: &[[f32; 3]],
) -> Vec<Correspondence> {
    pairings
        .iter()
        .filter_map(|p| correspondence(scan, p.query, &p.point, &p.information))
        .collect()
}

/// As [`correspondences_from_wire`] for pairings straight from the map: the same
/// values, bit for bit (the wire layout copies these fields unchanged).
pub fn correspondences_from_pairings(
    pairings: &[Pairing],
    scan: &[[f32; 3]],
) -> Vec<Correspondence> {
    pairings
        .iter()
        .filter_map(|p| correspondence(scan, p.query_index, &p.map_point, &p.information))
        .collect()
}

fn correspondence(
    scan: &[[f32; 3]],
    query: u32,
    map_point: &[f32; 3],
    information: &PackedSym3,
) -> Option<Correspondence> {
    Some(Correspondence {
        source: to_vec3(scan.get(query as usize)?),
        target: to_vec3(map_point),
        information: unpack_sym3(information),
    })
}

impl From<&Pairing> for WirePairing {
    fn from(p: &Pairing) -> Self {
        Self {
            query: p.query_index,
            local_index: p.local_index,
            keyframe: p.keyframe,
            point: p.map_point,
            dist_sq: p.dist_sq,
            information: p.information,
        }
    }
}
