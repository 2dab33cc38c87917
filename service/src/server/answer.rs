//! An answer to one request (header and pairings) and the small helpers every kind of
//! request builds its answer or its rejection with.

use std::mem::MaybeUninit;

use kfmap_map::map::{MapError, Pairing};
use kfmap_protocol::{Cov2CovMode, Rejection, ResponseHeader, StatusCode, WirePairing};
use rayon::prelude::*;

use super::limits::Limits;
use super::state::ServedMap;

/// A response: header and pairings.
#[derive(Debug, Clone, PartialEq)]
pub struct Answer {
    /// Status, timings, pose, gravity.
    pub header: ResponseHeader,
    /// Map points found.
    pub pairings: AnswerPairings,
}

/// The pairings of an answer. Cov2cov pairings stay as the map returns them until they
/// are written out, so the server converts them straight into shared memory.
#[derive(Debug, Clone, PartialEq)]
pub enum AnswerPairings {
    /// Already in the wire layout (nearest, radius).
    Wire(Vec<WirePairing>),
    /// Cov2cov pairings from the map.
    Cov2Cov(Vec<Pairing>),
}

impl Default for AnswerPairings {
    fn default() -> Self {
        Self::Wire(Vec::new())
    }
}

impl AnswerPairings {
    /// Number of pairings.
    pub fn len(&self) -> usize {
        match self {
            Self::Wire(v) => v.len(),
            Self::Cov2Cov(v) => v.len(),
        }
    }

    /// True without pairings.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Writes every pairing, in the wire layout, into `out` (exactly [`Self::len`] long).
    pub fn write(&self, out: &mut [MaybeUninit<WirePairing>]) {
        assert_eq!(
            out.len(),
            self.len(),
            "the response was loaned for another count"
        );
        match self {
            Self::Wire(v) => out.par_iter_mut().zip(v.par_iter()).for_each(|(slot, p)| {
                slot.write(*p);
            }),
            Self::Cov2Cov(v) => out.par_iter_mut().zip(v.par_iter()).for_each(|(slot, p)| {
                slot.write(WirePairing::from(p));
            }),
        }
    }

    /// The pairings in the wire layout.
    pub fn into_wire(self) -> Vec<WirePairing> {
        match self {
            Self::Wire(v) => v,
            Self::Cov2Cov(v) => v.par_iter().map(WirePairing::from).collect(),
        }
    }
}

impl Answer {
    /// An error answer.
    pub fn rejected(request_id: u64, rejection: &Rejection) -> Self {
        let mut header = ResponseHeader {
            request_id,
            status: rejection.status as u32,
            detail: rejection.detail,
            ..Default::default()
        };
        header.set_message(&rejection.message);
        Self {
            header,
            pairings: AnswerPairings::default(),
        }
    }
}

/// A `BadRequest` rejection saying what was wrong.
pub(super) fn bad(message: impl Into<String>) -> Rejection {
    Rejection::new(StatusCode::BadRequest, message)
}

/// An answer with `pairings` and the active keyframes they came from.
pub(super) fn with_active(pairings: AnswerPairings, active: &[u64]) -> Answer {
    let mut header = ResponseHeader::default();
    let used = active.len().min(header.active.len());
    header.active[..used].copy_from_slice(&active[..used]);
    header.active_len = used as u32;
    Answer { header, pairings }
}

/// A map failure inside a query: the server's fault, not the request's.
pub(super) fn map_error(e: MapError) -> Rejection {
    Rejection::new(StatusCode::Internal, format!("map: {e}"))
}

/// True when a request of wire mode `mode` is answered in exact mode: its own mode,
/// else the server's (`server.toml`), else the map's (`bake.toml`).
pub(super) fn exact_mode(map: &ServedMap, mode: u32, limits: &Limits) -> Result<bool, Rejection> {
    let requested = Cov2CovMode::from_code(mode).ok_or_else(|| {
        bad(format!(
            "cov2cov mode {mode} is unknown (0 map default, 1 approximate, 2 exact)"
        ))
    })?;
    Ok(matches!(
        (requested, limits.cov2cov_mode, map.exact_by_default),
        (Cov2CovMode::Exact, _, _)
            | (Cov2CovMode::MapDefault, Cov2CovMode::Exact, _)
            | (Cov2CovMode::MapDefault, Cov2CovMode::MapDefault, true)
    ))
}
