//! Per-frame and cumulative client statistics.
//!
//! The measures of thesis §3.7 and §4.6 (see docs/REFERENCES.md): rendered
//! blocks and triangles, quality factor, requests in flight / sent /
//! cancelled, bytes received and dropped, and the "relevant data" ratio
//! (§3.7: "more than 95 % of received data are immediately used for
//! rendering"): bytes of records that were applied and drawn at their new LOD
//! in the frame they were applied, over all bytes received. Beyond the thesis:
//! the screen-space error (max and mean over drawn blocks), see
//! [`crate::importance::screen_space_error`].

/// Statistics of one frame.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrameStats {
    /// Frame number (starting at 1).
    pub frame: u64,
    /// Elevation blocks drawn.
    pub blocks_drawn: usize,
    /// Triangles drawn (`2·w²` per block at its drawn LOD, `w` = W or W/2).
    pub triangles: u64,
    /// Quality factor used for this frame's selection.
    pub quality_factor: f64,
    /// Requests in flight after this frame's selection.
    pub in_flight: usize,
    /// Requests sent this frame.
    pub sent: usize,
    /// Requests cancelled this frame.
    pub cancelled: usize,
    /// Records decoded and applied at this frame's start.
    pub refines_applied: usize,
    /// Splits executed at this frame's start.
    pub splits: usize,
    /// Merges executed at this frame's start.
    pub merges: usize,
    /// Bytes delivered since the previous frame.
    pub bytes_received: u64,
    /// Of those, bytes dropped (cancelled, stale or already loaded).
    pub bytes_dropped: u64,
    /// Of those, bytes of child tables after a record
    /// ([`crate::lookahead`]).
    pub bytes_tables: u64,
    /// Records rejected (corrupt, wrong block) since the previous frame.
    pub records_rejected: usize,
    /// Largest screen-space error (pixels) over drawn blocks.
    pub max_screen_error: f64,
    /// Mean screen-space error (pixels) over drawn blocks.
    pub mean_screen_error: f64,
    /// Mean screen-space error (pixels) over the screen: drawn blocks
    /// weighted by their approximate screen area.
    pub pixel_mean_screen_error: f64,
    /// Nodes in both trees after this frame's operations.
    pub nodes: usize,
    /// Near plane distance used.
    pub near: f64,
    /// Far plane distance used.
    pub far: f64,
    /// Cumulative totals.
    pub totals: Totals,
}

/// Cumulative counters since the client started.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Totals {
    /// Requests sent.
    pub sent: u64,
    /// Requests cancelled.
    pub cancelled: u64,
    /// Bytes received (all deliveries).
    pub bytes_received: u64,
    /// Bytes dropped without being applied.
    pub bytes_dropped: u64,
    /// Bytes of rejected records.
    pub bytes_rejected: u64,
    /// Bytes of child tables received after records ([`crate::lookahead`]).
    /// A table counts with the relevant bytes (or those drawn later) when a
    /// record asked through it was drawn on arrival (later): its references
    /// were needed to draw, as the references inside a record count with
    /// the record. The others are wasted.
    pub bytes_tables: u64,
    /// Of those, the bytes of tables counted as used.
    pub bytes_tables_used: u64,
    /// Bytes of records applied and drawn at their new LOD on arrival.
    pub bytes_relevant: u64,
    /// Bytes of records applied, not drawn on arrival, that were loaded for
    /// a neighbour's split (thesis §4.3.3: a visible block may split only
    /// when its neighbours are at most the crack fixing's level difference
    /// coarser, so an invisible coarse neighbour is refined first). Part of
    /// the irrelevant bytes; the rest is `received − relevant − forced`.
    pub bytes_forced: u64,
    /// Bytes of records applied, not drawn on arrival, and drawn at their
    /// new LOD in a later frame. What was received and is neither this nor
    /// relevant was never drawn: wasted ([`Totals::wasted_ratio`]).
    pub bytes_drawn_later: u64,
    /// Records applied.
    pub refines_applied: u64,
    /// Records rejected.
    pub records_rejected: u64,
}

impl Totals {
    /// Relevant bytes over received bytes (1 when nothing was received).
    pub fn relevant_ratio(&self) -> f64 {
        if self.bytes_received == 0 {
            1.0
        } else {
            self.bytes_relevant as f64 / self.bytes_received as f64
        }
    }

    /// Bytes received and never drawn (so far: dropped, rejected, not yet
    /// or never drawn) over received bytes (0 when nothing was received).
    pub fn wasted_ratio(&self) -> f64 {
        if self.bytes_received == 0 {
            0.0
        } else {
            let used = self.bytes_relevant + self.bytes_drawn_later;
            self.bytes_received.saturating_sub(used) as f64 / self.bytes_received as f64
        }
    }

    /// Bytes dropped on arrival or rejected (cancelled, stale, already
    /// loaded, corrupt) over received bytes: the part of
    /// [`Totals::wasted_ratio`] that was never applied (0 when nothing was
    /// received).
    pub fn dropped_ratio(&self) -> f64 {
        if self.bytes_received == 0 {
            0.0
        } else {
            (self.bytes_dropped + self.bytes_rejected) as f64 / self.bytes_received as f64
        }
    }

    /// Bytes of child tables never used over received bytes: the part of
    /// [`Totals::wasted_ratio`] that traveled for asking ahead (0 when
    /// nothing was received).
    pub fn unused_tables_ratio(&self) -> f64 {
        if self.bytes_received == 0 {
            0.0
        } else {
            self.bytes_tables.saturating_sub(self.bytes_tables_used) as f64
                / self.bytes_received as f64
        }
    }

    /// Bytes of forced neighbour refines not drawn on arrival over received
    /// bytes (0 when nothing was received).
    pub fn forced_ratio(&self) -> f64 {
        if self.bytes_received == 0 {
            0.0
        } else {
            self.bytes_forced as f64 / self.bytes_received as f64
        }
    }
}
