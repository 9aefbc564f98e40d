//! Train tables merged while the phase still renders: the canonical prefix, folded as the
//! uploads are accepted.
//!
//! The train barrier ([`crate::finish`]) merges a phase's tables in canonical task order
//! (`seq`) and solves. That merge is a left fold — each cell's record is its first table's
//! record with the later tables' records merged into it, in order
//! ([`protocol::cv::merge_train`]) — so every contiguous prefix `0..n` of the phase can be
//! folded as soon as its tables are accepted, while the workers render the rest. The
//! barrier then finds the fold done and only solves: the same bits as merging everything at
//! the barrier, without reading the tables back from the store and decoding them again.
//!
//! **A cache, not state.** It holds decoded copies of results that are already stored, is
//! filled only by the uploads this process accepts, and the barrier uses it only when it
//! covers every task of the phase with no error; otherwise — after a restart, when another
//! coordinator on the same database accepted some of the results, after a layout or merge
//! error — the barrier reads the store as before. Nothing a restart needs lives here.
//!
//! An upload [reserves](TrainMerges::reserve) its place *before* it stores its result, so
//! a barrier that starts after the phase's last result was stored waits for every accepted
//! table still being folded (briefly: a fold of one table is milliseconds) instead of
//! missing it. At most [`MAX_PHASES`] phases are tracked; the oldest is dropped (e.g. a
//! cancelled job's).

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use estimators::table::AccumulatorTable;

/// Phases (of any jobs) tracked at once.
pub const MAX_PHASES: usize = 8;

/// How long [`TrainMerges::take`] waits for reserved tables before the barrier reads the
/// store instead.
const WAIT: Duration = Duration::from_secs(5);

/// The fold of one phase's accepted tables.
#[derive(Debug, Default)]
struct Prefix {
    /// Seq of the next table to fold.
    next: i64,
    /// The fold of tables `0..next`.
    merged: Option<AccumulatorTable>,
    /// Layout signature of the folded tables ([`protocol::cv::layout_signature`]).
    layout: Option<String>,
    /// Accepted tables that arrived ahead of `next`.
    ahead: BTreeMap<i64, AccumulatorTable>,
    /// Uploads that reserved a place and have not offered or given it up.
    reserved: usize,
    /// A table did not fold (layout mismatch, repeated seq): the barrier must read the store.
    failed: bool,
}

impl Prefix {
    fn fold(&mut self, seq: i64, table: AccumulatorTable) {
        if self.failed {
            return;
        }
        if seq < self.next || self.ahead.contains_key(&seq) {
            self.failed = true;
            return;
        }
        self.ahead.insert(seq, table);
        while let Some(t) = self.ahead.remove(&self.next) {
            if !self.fold_next(t) {
                self.failed = true;
                self.ahead.clear();
                self.merged = None;
                return;
            }
            self.next += 1;
        }
    }

    /// Folds the next table in order; false on a layout mismatch (the checks of
    /// [`protocol::cv::merge_train`]).
    fn fold_next(&mut self, t: AccumulatorTable) -> bool {
        let Ok(sig) = protocol::cv::layout_signature(&t) else {
            return false;
        };
        if let (Some(have), Some(sig)) = (&self.layout, &sig)
            && have != sig
        {
            return false;
        }
        if self.layout.is_none() {
            self.layout = sig;
        }
        match &mut self.merged {
            None => {
                self.merged = Some(t);
                true
            }
            Some(m) => m.kind() == t.kind() && m.merge_owned(t).is_ok(),
        }
    }
}

type Entry = Arc<(Mutex<Prefix>, tokio::sync::Notify)>;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // Every statement leaves the data consistent (at worst `failed`): a poisoned lock is
    // still usable.
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// The train phases this process is folding, keyed by (job, phase index).
#[derive(Debug, Default)]
pub struct TrainMerges(Mutex<VecDeque<((i64, i64), Entry)>>);

impl TrainMerges {
    fn entry(&self, key: (i64, i64), create: bool) -> Option<Entry> {
        let mut all = lock(&self.0);
        if let Some((_, e)) = all.iter().find(|(k, _)| *k == key) {
            return Some(e.clone());
        }
        if !create {
            return None;
        }
        if all.len() >= MAX_PHASES {
            all.pop_front();
        }
        let e: Entry = Arc::default();
        all.push_back((key, e.clone()));
        Some(e)
    }

    /// Reserves a place for a train result of (`job`, `phase`) about to be stored. Offer
    /// the decoded table once the result is accepted ([`Reservation::offer`]); dropping the
    /// reservation (rejected, duplicate, error) gives the place up.
    pub fn reserve(&self, job: i64, phase: i64) -> Reservation {
        let entry = self.entry((job, phase), true).expect("created");
        lock(&entry.0).reserved += 1;
        Reservation { entry: Some(entry) }
    }

    /// The fold of all `tasks` tables of (`job`, `phase`), when this process accepted and
    /// folded every one of them; `None` sends the barrier to the store. Waits (up to a few
    /// seconds) for reserved tables still being folded. Forgets the phase either way.
    pub async fn take(&self, job: i64, phase: i64, tasks: i64) -> Option<AccumulatorTable> {
        let key = (job, phase);
        let entry = self.entry(key, false)?;
        let deadline = tokio::time::Instant::now() + WAIT;
        let out = loop {
            let notified = entry.1.notified();
            {
                let mut p = lock(&entry.0);
                if p.reserved == 0 {
                    let done = !p.failed && p.next == tasks && p.ahead.is_empty();
                    break if done { p.merged.take() } else { None };
                }
            }
            if tokio::time::timeout_at(deadline, notified).await.is_err() {
                break None;
            }
        };
        lock(&self.0).retain(|(k, e)| *k != key || !Arc::ptr_eq(e, &entry));
        out
    }
}

/// A reserved place in a phase's fold ([`TrainMerges::reserve`]).
#[derive(Debug)]
pub struct Reservation {
    entry: Option<Entry>,
}

impl Reservation {
    /// Folds the accepted table of task `seq` (CPU work: call it on a blocking thread).
    pub fn offer(mut self, seq: i64, table: AccumulatorTable) {
        if let Some(e) = self.entry.take() {
            let mut p = lock(&e.0);
            p.fold(seq, table);
            p.reserved -= 1;
            drop(p);
            e.1.notify_waiters();
        }
    }
}

impl Drop for Reservation {
    fn drop(&mut self) {
        if let Some(e) = self.entry.take() {
            lock(&e.0).reserved -= 1;
            e.1.notify_waiters();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use estimators::cell::{CellAccumulator, ColorMode, ComponentLayout, CvSample};
    use std::collections::BTreeMap;

    /// A moments table with `cells` cells whose values depend on `salt`.
    fn table(salt: u64, cells: u64, partitions: u32) -> AccumulatorTable {
        let layout = ComponentLayout::new(partitions, 1).expect("layout");
        let mut t = BTreeMap::new();
        for k in 0..cells {
            let mut a = CellAccumulator::new(layout, ColorMode::Rgb);
            for i in 0..3u64 {
                let x = ((salt * 31 + k * 7 + i) % 17) as f64 / 17.0 + 0.1;
                let bsdf = [0.5 * x + 0.1];
                let s = CvSample {
                    pdf: 1.0 + x,
                    partition: Some(((i % u64::from(partitions)) as u32, x)),
                    overlapping: &bsdf,
                };
                a.add(1.0 + x, [x, 0.5 * x, 2.0 * x], &s).expect("sample");
            }
            t.insert(k + salt % 3, a);
        }
        AccumulatorTable::Moments(t, Some(0.1 + 0.3 * salt as f64))
    }

    fn merged_at_barrier(tables: &[AccumulatorTable]) -> AccumulatorTable {
        let kind = tables[0].kind();
        protocol::cv::merge_train(kind, tables.to_vec(), 2).expect("merge")
    }

    #[tokio::test]
    async fn the_fold_in_any_arrival_order_equals_the_barrier_merge() {
        let tables: Vec<_> = (0..4).map(|s| table(s, 5, 2)).collect();
        let want = merged_at_barrier(&tables);
        for order in [[0, 1, 2, 3], [3, 2, 1, 0], [1, 3, 0, 2]] {
            let m = TrainMerges::default();
            let places: Vec<_> = (0..4).map(|_| m.reserve(7, 1)).collect();
            for (place, &seq) in places.into_iter().zip(&order) {
                place.offer(seq, tables[seq as usize].clone());
            }
            let got = m.take(7, 1, 4).await.expect("complete fold");
            assert_eq!(got, want, "order {order:?}");
            assert!(m.take(7, 1, 4).await.is_none(), "taken once");
        }
    }

    #[tokio::test]
    async fn an_incomplete_or_failed_fold_sends_the_barrier_to_the_store() {
        let m = TrainMerges::default();
        m.reserve(1, 1).offer(0, table(0, 3, 2));
        m.reserve(1, 1).offer(2, table(2, 3, 2));
        assert!(m.take(1, 1, 3).await.is_none(), "seq 1 missing");
        // A table of another layout.
        m.reserve(2, 1).offer(0, table(0, 3, 2));
        m.reserve(2, 1).offer(1, table(1, 3, 3));
        assert!(m.take(2, 1, 2).await.is_none(), "layout mismatch");
        // The same seq twice.
        m.reserve(3, 1).offer(0, table(0, 3, 2));
        m.reserve(3, 1).offer(0, table(0, 3, 2));
        assert!(m.take(3, 1, 1).await.is_none(), "repeated seq");
        // A given-up reservation does not count, and unknown phases have nothing.
        m.reserve(4, 1).offer(0, table(0, 3, 2));
        drop(m.reserve(4, 1));
        assert!(m.take(4, 1, 1).await.is_some());
        assert!(m.take(5, 1, 1).await.is_none());
    }

    #[tokio::test]
    async fn the_barrier_waits_for_a_reserved_table() {
        let m = Arc::new(TrainMerges::default());
        m.reserve(9, 1).offer(0, table(0, 3, 2));
        let late = m.reserve(9, 1);
        let m2 = m.clone();
        let taker = tokio::spawn(async move { m2.take(9, 1, 2).await });
        tokio::time::sleep(Duration::from_millis(50)).await;
        assert!(!taker.is_finished(), "took before the reserved table came");
        late.offer(1, table(1, 3, 2));
        let got = taker.await.expect("join").expect("complete fold");
        assert_eq!(got, merged_at_barrier(&[table(0, 3, 2), table(1, 3, 2)]));
    }

    #[test]
    fn at_most_max_phases_are_kept() {
        let m = TrainMerges::default();
        for job in 0..(MAX_PHASES as i64 + 3) {
            m.reserve(job, 1).offer(0, table(0, 2, 2));
        }
        assert_eq!(lock(&m.0).len(), MAX_PHASES);
        assert!(m.entry((0, 1), false).is_none(), "the oldest was dropped");
    }
}
