//! The board's learning feedforward from the host (`Request::Learn`,
//! [`twinstack::services::learning`]): configure it, switch it, read its status, and read and
//! write its table — the host's copy of what the board learned, to keep beside the motion it
//! was learned on and to play again later (written, then posted: it plays from the next
//! period boundary).
//!
//! A table is one value a tick of the period, the correction added to the feedforward, Q2.30
//! normalised drive; the board limits each written value to the configured limit.

use crate::client::{Client, LinkError};
use crate::Transport;
use twinstack::protocol::messages::{
    LearnRequest, LearnState, LearnStatus, Request, Response, MAX_CHUNK,
};
use twinstack::services::learning::LearnSettings;

/// Why a table could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum TableError {
    /// The link, or the board's refusal.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// No period configured: the board has no table.
    #[error("the learning has no period configured (configure it first)")]
    NotConfigured,
    /// A table to write that is not one value a tick of the configured period.
    #[error(
        "a table of {got} values for a period of {period} ticks: one value a tick of the period"
    )]
    Length {
        /// Values given.
        got: usize,
        /// The configured period, ticks.
        period: u16,
    },
}

/// Sends `request`; a NACK is [`LinkError::Nack`].
fn learn<T: Transport>(
    client: &mut Client<T>,
    request: LearnRequest,
) -> Result<Response, LinkError> {
    match client.request(&Request::Learn(request))? {
        Response::Nack { reason } => Err(LinkError::Nack {
            request: "Learn",
            reason,
        }),
        other => Ok(other),
    }
}

/// Expects an ACK to `request`.
fn acknowledged<T: Transport>(
    client: &mut Client<T>,
    request: LearnRequest,
) -> Result<(), LinkError> {
    match learn(client, request)? {
        Response::Ack { .. } => Ok(()),
        other => Err(LinkError::Unexpected {
            request: "Learn",
            got: format!("{other:?}"),
        }),
    }
}

/// Sets the learning's period, gain, robustness filter, lead and limit (the board validates
/// them, a refusal naming the `learning.*` field; the period restarts at bin 0).
pub fn configure<T: Transport>(
    client: &mut Client<T>,
    settings: LearnSettings,
) -> Result<(), LinkError> {
    acknowledged(client, LearnRequest::Configure(settings))
}

/// Switches the learning off, to learning (a sensor and a configuration needed) or frozen (the
/// table plays without updating).
pub fn set_state<T: Transport>(client: &mut Client<T>, state: LearnState) -> Result<(), LinkError> {
    acknowledged(client, LearnRequest::State(state))
}

/// Zeroes the table (it plays from the next period boundary).
pub fn reset<T: Transport>(client: &mut Client<T>) -> Result<(), LinkError> {
    acknowledged(client, LearnRequest::Reset)
}

/// The learning's state, its period and its last period's error.
pub fn status<T: Transport>(client: &mut Client<T>) -> Result<LearnStatus, LinkError> {
    match learn(client, LearnRequest::Status)? {
        Response::Learn(s) => Ok(s),
        other => Err(LinkError::Unexpected {
            request: "Learn",
            got: format!("{other:?}"),
        }),
    }
}

/// The table playing now, one Q2.30 value a tick of the configured period, read in pieces.
pub fn read_table<T: Transport>(client: &mut Client<T>) -> Result<Vec<i32>, TableError> {
    let period = status(client)?.period_ticks;
    if period == 0 {
        return Err(TableError::NotConfigured);
    }
    let mut table = Vec::with_capacity(period as usize);
    while table.len() < period as usize {
        match learn(
            client,
            LearnRequest::ReadTable {
                offset: table.len() as u32,
            },
        )? {
            Response::RecordChunk { values, .. } if !values.is_empty() => table.extend(values),
            other => {
                return Err(LinkError::Unexpected {
                    request: "Learn",
                    got: format!("{other:?}"),
                }
                .into())
            }
        }
    }
    table.truncate(period as usize);
    Ok(table)
}

/// Writes `table` (one Q2.30 value a tick of the configured period) in pieces and posts it:
/// it plays from the next period boundary, in the learning's state (frozen: as it is;
/// learning: as the start of further learning).
pub fn write_table<T: Transport>(client: &mut Client<T>, table: &[i32]) -> Result<(), TableError> {
    let period = status(client)?.period_ticks;
    if period == 0 {
        return Err(TableError::NotConfigured);
    }
    if table.len() != period as usize {
        return Err(TableError::Length {
            got: table.len(),
            period,
        });
    }
    for (k, piece) in table.chunks(MAX_CHUNK).enumerate() {
        let values = heapless::Vec::from_slice(piece).map_err(|_| LinkError::Unexpected {
            request: "Learn",
            got: format!("a piece of {} values", piece.len()),
        })?;
        acknowledged(
            client,
            LearnRequest::WriteTable {
                offset: (k * MAX_CHUNK) as u32,
                values,
            },
        )?;
    }
    acknowledged(client, LearnRequest::PostTable)?;
    Ok(())
}
