//! The bytes of parsed pieces queued between a worker's peer readers and its frame loop.
//!
//! A reader reserves a piece's bytes before it decompresses or parses the piece, and the
//! reservation travels with the piece until the frame loop has handed it to the exchange
//! (which bounds what it holds itself, `ExchangeLimits::pending_bytes`). So a peer that
//! floods pieces, or sends small LZ4 blocks that state large pieces, stalls the readers
//! (all of them: the budget is shared, and served first come, first served) once the
//! budget is spent, and through QUIC flow control itself, instead of growing this worker's
//! memory; a queue bounded only by its count of pieces held 64 of the largest. Every
//! reservation is granted once the frame loop drains the queue, which it does whenever a
//! frame runs.

use std::sync::Arc;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// Budgets are kept in units of this many bytes (semaphore permits are counted in `u32`).
const UNIT: u64 = 1024;

/// A byte budget shared by all of a worker's peer readers.
#[derive(Clone)]
pub struct PieceBudget {
    permits: Arc<Semaphore>,
    units: u32,
}

impl PieceBudget {
    /// A budget of `bytes` (at least one unit, at most `u32::MAX` units).
    pub fn new(bytes: u64) -> Self {
        let units = bytes.div_ceil(UNIT).clamp(1, u32::MAX as u64) as u32;
        PieceBudget {
            permits: Arc::new(Semaphore::new(units as usize)),
            units,
        }
    }

    /// Waits until `bytes` of the budget are free and reserves them until the returned
    /// permit drops. A piece larger than the whole budget reserves all of it (it then waits
    /// for every earlier piece to be consumed, and cannot wait forever).
    pub async fn reserve(&self, bytes: u64) -> OwnedSemaphorePermit {
        let units = bytes.div_ceil(UNIT).clamp(1, self.units as u64) as u32;
        self.permits
            .clone()
            .acquire_many_owned(units)
            .await
            .expect("the budget's semaphore is never closed")
    }

    /// Bytes free now.
    pub fn free(&self) -> u64 {
        self.permits.available_permits() as u64 * UNIT
    }
}

#[cfg(test)]
mod tests {
    use super::PieceBudget;
    use std::time::Duration;

    #[tokio::test]
    async fn a_spent_budget_stalls_the_next_piece_until_one_is_consumed() {
        let b = PieceBudget::new(10 * 1024);
        let first = b.reserve(6 * 1024).await;
        let second = b.reserve(4000).await;
        assert_eq!(b.free(), 0);
        // A third piece waits: nothing was consumed.
        let third = tokio::time::timeout(Duration::from_millis(50), b.reserve(1)).await;
        assert!(third.is_err(), "reserved past the budget");
        drop(second);
        assert_eq!(b.free(), 4 * 1024);
        let third = tokio::time::timeout(Duration::from_secs(5), b.reserve(1)).await;
        assert!(third.is_ok());
        drop(first);
        drop(third);
        assert_eq!(b.free(), 10 * 1024);
    }

    #[tokio::test]
    async fn a_piece_past_the_whole_budget_takes_all_of_it_and_does_not_wait_forever() {
        let b = PieceBudget::new(8 * 1024);
        let small = b.reserve(1).await;
        let b2 = b.clone();
        let big = tokio::spawn(async move { b2.reserve(1 << 40).await });
        tokio::time::sleep(Duration::from_millis(50)).await;
        assert!(
            !big.is_finished(),
            "took the budget while a piece held part of it"
        );
        drop(small);
        let big = tokio::time::timeout(Duration::from_secs(5), big)
            .await
            .expect("the large piece waited forever")
            .unwrap();
        assert_eq!(b.free(), 0);
        drop(big);
        assert_eq!(b.free(), 8 * 1024);
    }
}
