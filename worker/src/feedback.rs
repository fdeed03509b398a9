//! Feedback: which pages rays needed, at the level their footprint called for.
//!
//! While casting, each ray appends the key of every page it enters (at the requested
//! level) to its tile's list; rays that stopped early append nothing more, so data hidden
//! behind opaque content is never requested and stays coarse. A tile's list is reduced to
//! `(page, rays)` pairs; the frame's lists are merged into [`Feedback`], whose counts are
//! the pixel coverage of each page. [`Feedback::priorities`] then makes every ancestor of a
//! requested page at least as important as the page (a child never outranks its parent),
//! which keeps the fallback chain resident and loads coarse data first.

use bytemuck::{Pod, Zeroable};
use std::collections::HashMap;
use strata_common::ids::PageId;

/// One reduced feedback record (the layout a GPU feedback buffer reduces to).
#[repr(C)]
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct FeedbackEntry {
    /// Page key (data set, level, Morton index).
    pub page: u64,
    /// Rays (pixels) that requested the page.
    pub coverage: u32,
    /// Padding to 16 bytes.
    pub _pad: u32,
}

/// A tile's page requests as its rays make them: runs of the same page (neighbouring rays
/// entering the same brick one after another) are kept as one record with a count, so a
/// tile's list stays short and cheap to sort.
#[derive(Clone, Debug, Default)]
pub struct Requests {
    runs: Vec<(u64, u32)>,
}

impl Requests {
    /// An empty list.
    pub fn new() -> Self {
        Self::default()
    }

    /// One request of `page`.
    #[inline]
    pub fn push(&mut self, page: u64) {
        match self.runs.last_mut() {
            Some((k, n)) if *k == page => *n += 1,
            _ => self.runs.push((page, 1)),
        }
    }

    /// Requests made (a page requested twice counts twice).
    pub fn len(&self) -> usize {
        self.runs.iter().map(|r| r.1 as usize).sum()
    }

    /// Whether none were made.
    pub fn is_empty(&self) -> bool {
        self.runs.is_empty()
    }

    /// Every request, in order, one key per request.
    pub fn keys(&self) -> impl Iterator<Item = u64> + '_ {
        self.runs
            .iter()
            .flat_map(|&(k, n)| std::iter::repeat_n(k, n as usize))
    }
}

/// Reduces a tile's requests into sorted `(page, count)` records.
pub fn reduce_tile(raw: &mut Requests) -> Vec<FeedbackEntry> {
    raw.runs.sort_unstable_by_key(|r| r.0);
    let mut out: Vec<FeedbackEntry> = Vec::new();
    for &(k, n) in raw.runs.iter() {
        match out.last_mut() {
            Some(e) if e.page == k => e.coverage += n,
            _ => out.push(FeedbackEntry {
                page: k,
                coverage: n,
                _pad: 0,
            }),
        }
    }
    out
}

/// A frame's feedback: requested pages and their pixel coverage.
#[derive(Clone, Debug, Default)]
pub struct Feedback {
    /// Coverage by page key.
    pub coverage: HashMap<u64, u32>,
}

impl Feedback {
    /// Adds a tile's records.
    pub fn add(&mut self, entries: &[FeedbackEntry]) {
        for e in entries {
            *self.coverage.entry(e.page).or_insert(0) += e.coverage;
        }
    }

    /// Merges another frame part.
    pub fn merge(&mut self, o: &Feedback) {
        for (&k, &c) in &o.coverage {
            *self.coverage.entry(k).or_insert(0) += c;
        }
    }

    /// Number of distinct requested pages.
    pub fn len(&self) -> usize {
        self.coverage.len()
    }

    /// Whether nothing was requested.
    pub fn is_empty(&self) -> bool {
        self.coverage.is_empty()
    }

    /// Requested pages and all their ancestors with priorities, most important first.
    /// `parent(key)` gives a page's parent key (None at a root). Each ancestor's priority is
    /// the maximum over its requested descendants and itself; ties put coarser pages first.
    pub fn priorities(&self, parent: impl Fn(u64) -> Option<u64>) -> Vec<(u64, u32)> {
        let mut prio: HashMap<u64, u32> = self.coverage.clone();
        for (&k, &c) in &self.coverage {
            let mut p = parent(k);
            while let Some(pk) = p {
                let e = prio.entry(pk).or_insert(0);
                // An ancestor already at >= c either got there by propagation (so its own
                // ancestors are >= c too) or is itself requested (and its own walk raises
                // them): either way the walk can stop.
                if *e >= c {
                    break;
                }
                *e = c;
                p = parent(pk);
            }
        }
        let mut v: Vec<(u64, u32)> = prio.into_iter().collect();
        v.sort_by(|a, b| {
            b.1.cmp(&a.1)
                .then(PageId(b.0).level().cmp(&PageId(a.0).level()))
                .then(a.0.cmp(&b.0))
        });
        v
    }
}

/// Where a cast's time went, page by page: each tile's `seconds` divided among the pages
/// its rays entered, in proportion to the rays that entered each (its `coverage`), summed
/// over the tiles and divided by all the tiles' seconds. Returns `(page, share)` sorted by
/// page; the shares add up to at most 1 (tiles whose rays entered no page, and tiles of no
/// measurable time, give theirs to no page). Empty when no tile took any time.
///
/// A ray that enters a brick samples it from entry to exit or to where it terminates, so
/// rays entered is the page's share of the tile's samples up to the brick lengths; what
/// the tile's rays spend outside pages (set-up, skipping transparent bricks, horizons
/// without a page) is spread in the same proportion.
pub fn page_shares<'a>(
    tiles: impl IntoIterator<Item = (&'a [FeedbackEntry], f64)>,
) -> Vec<(u64, f32)> {
    let mut by_page: HashMap<u64, f64> = HashMap::new();
    let mut total = 0.0;
    for (entries, seconds) in tiles {
        if !(seconds.is_finite() && seconds > 0.0) {
            continue;
        }
        total += seconds;
        let rays: u64 = entries.iter().map(|e| e.coverage as u64).sum();
        if rays == 0 {
            continue;
        }
        let per_ray = seconds / rays as f64;
        for e in entries.iter().filter(|e| e.coverage > 0) {
            *by_page.entry(e.page).or_default() += per_ray * e.coverage as f64;
        }
    }
    if !(total > 0.0) {
        return Vec::new();
    }
    let mut out: Vec<(u64, f32)> = by_page
        .into_iter()
        .map(|(k, s)| (k, (s / total) as f32))
        .filter(|&(_, s)| s > 0.0)
        .collect();
    out.sort_unstable_by_key(|r| r.0);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(page: u64, coverage: u32) -> FeedbackEntry {
        FeedbackEntry {
            page,
            coverage,
            _pad: 0,
        }
    }

    #[test]
    fn page_shares_divide_each_tiles_time_by_rays() {
        // Tile A: 3 s, page 1 entered by 1 ray and page 2 by 2; tile B: 1 s, page 2 only;
        // tile C: 4 s and no page (its rays met only transparent bricks); tile D: no time.
        let a = [entry(1, 1), entry(2, 2)];
        let b = [entry(2, 5)];
        let d = [entry(9, 4)];
        let s = page_shares([(&a[..], 3.0), (&b[..], 1.0), (&[][..], 4.0), (&d[..], 0.0)]);
        assert_eq!(s.len(), 2);
        assert_eq!(s[0].0, 1);
        assert_eq!(s[1].0, 2);
        // Page 1: 1 s of 8; page 2: 2 + 1 s of 8; the 4 s of tile C go to no page.
        assert!((s[0].1 - 1.0 / 8.0).abs() < 1e-7, "{s:?}");
        assert!((s[1].1 - 3.0 / 8.0).abs() < 1e-7, "{s:?}");
        assert!(page_shares([(&b[..], 0.0)]).is_empty());
        assert!(page_shares([(&b[..], f64::NAN), (&a[..], f64::INFINITY)]).is_empty());
    }

    #[test]
    fn tiles_reduce_to_counts() {
        let mut raw = Requests::new();
        for k in [5, 3, 5, 5, 9, 3, 3] {
            raw.push(k);
        }
        assert_eq!(raw.len(), 7);
        assert_eq!(raw.keys().collect::<Vec<_>>(), [5, 3, 5, 5, 9, 3, 3]);
        let r = reduce_tile(&mut raw);
        assert_eq!(
            r.iter().map(|e| (e.page, e.coverage)).collect::<Vec<_>>(),
            vec![(3, 3), (5, 3), (9, 1)]
        );
    }

    #[test]
    fn child_never_above_parent() {
        // Keys: level in PageId bits; build a little tree by hand.
        let leaf = |m| PageId::new(0, 0, m).0;
        let mid = |m| PageId::new(0, 1, m).0;
        let root = PageId::new(0, 2, 0).0;
        let parent = |k: u64| {
            let id = PageId(k);
            match id.level() {
                0 => Some(mid(id.morton() / 8)),
                1 => Some(root),
                _ => None,
            }
        };
        let mut f = Feedback::default();
        f.coverage.insert(leaf(0), 10);
        f.coverage.insert(leaf(9), 40);
        f.coverage.insert(mid(0), 3);
        let p = f.priorities(parent);
        let get = |k| p.iter().find(|e| e.0 == k).unwrap().1;
        assert_eq!(get(root), 40);
        assert_eq!(get(mid(1)), 40);
        assert_eq!(get(mid(0)), 10);
        assert_eq!(p[0].0, root, "coarser first among equals");
        for &(k, c) in &p {
            if let Some(pk) = parent(k) {
                assert!(get(pk) >= c);
            }
        }
    }
}
