//! The page cache: its promises (prefetched pages never evict, real requests evict the
//! least recently used unlocked pages and go before queued prefetches), and a race of its
//! loader threads: a real request for a page whose prefetch is already loading queues it
//! again, so two loaders can read the same page at once; the request must be counted done
//! exactly once (the race once underflowed the outstanding count and poisoned the cache,
//! seen in a distributed sequence test).

use std::sync::Arc;
use std::time::Duration;
use strata_common::geo::Affine3;
use strata_common::store::PageStore;
use strata_tests::scenes::volume_store;
use strata_worker::cache::{Class, PageCache};
use tempfile::TempDir;

/// A 96³ store in 32³ pages (more than 20 of them, all levels) and its page keys.
fn store_of_pages(dir: &std::path::Path) -> (Arc<PageStore>, Vec<u64>) {
    let n = 96u64;
    let data: Vec<f32> = (0..n * n * n).map(|i| (i % 251) as f32).collect();
    let p = volume_store(dir, "v", [n, n, n], data, Affine3::IDENTITY, 32);
    let store = Arc::new(PageStore::open(&p).unwrap());
    let keys: Vec<u64> = store.index().iter().map(|e| e.id.0).collect();
    assert!(keys.len() > 20);
    (store, keys)
}

#[test]
fn a_real_request_for_a_page_being_prefetched_is_counted_once() {
    let dir = TempDir::new().unwrap();
    let (store, keys) = store_of_pages(dir.path());
    // The last page is kept back for a request after the race.
    let (&last, keys) = keys.split_last().unwrap();
    for _ in 0..100 {
        let cache = PageCache::new(vec![store.clone()], 1 << 30, 2);
        for &k in keys {
            cache.request(k, Class::Prefetch, 1.0);
        }
        // Upgrade every page while the loaders are busy with the prefetches.
        for &k in keys {
            cache.request(k, Class::Real, 2.0);
        }
        cache.wait_real(Duration::from_secs(60)).unwrap();
        for &k in keys {
            assert!(cache.get(k).is_some(), "page {k:#x} not loaded");
        }
        // The cache still works: a count decremented twice (wrapped, or a loader panicked
        // on the overflow and poisoned the state) would make this wait fail or time out.
        cache.request(last, Class::Real, 3.0);
        cache.wait_real(Duration::from_secs(30)).unwrap();
        assert!(cache.get(last).is_some());
        // A loader that panicked (a count decremented twice overflows in a test build) has
        // stopped; the cache would go on with the other unseen.
        assert_eq!(cache.loaders_running(), 2);
    }
}

/// The cache's two promises (module docs of `strata_worker::cache`): prefetched pages never
/// evict anything, and real requests evict the least recently used unlocked pages; and
/// real requests outrank queued prefetches.
#[test]
fn prefetch_never_evicts_real_requests_evict_lru_and_go_first() {
    let dir = TempDir::new().unwrap();
    let (store, keys) = store_of_pages(dir.path());
    let page = strata_worker::cache::decoded_page_bytes(&store);

    // Room for three pages, holding three.
    let cache = PageCache::new(vec![store.clone()], 3 * page, 1);
    for &k in &keys[..3] {
        cache.request(k, Class::Real, 1.0);
    }
    cache.wait_real(Duration::from_secs(30)).unwrap();
    // Three real requests, none held: three misses, three reads.
    let s = cache.stats();
    assert_eq!((s.hits, s.misses, s.pages_read), (0, 3, 3), "{s:?}");
    // Five prefetches into the full cache are dropped before they are read: nothing is
    // evicted for them, and the disk is not asked (they were read and thrown away).
    for &k in &keys[3..8] {
        cache.request(k, Class::Prefetch, 1.0);
    }
    let t = std::time::Instant::now();
    while cache.stats().prefetch_dropped < 5 {
        assert!(t.elapsed() < Duration::from_secs(30), "{:?}", cache.stats());
        std::thread::sleep(Duration::from_millis(2));
    }
    let s = cache.stats();
    assert_eq!(
        (s.evictions, s.prefetch_dropped, s.pages_read),
        (0, 5, 3),
        "{s:?}"
    );
    // A real request for a held page is a hit, and reads nothing.
    cache.request(keys[1], Class::Real, 1.0);
    cache.wait_real(Duration::from_secs(30)).unwrap();
    let s = cache.stats();
    assert_eq!((s.hits, s.misses, s.pages_read), (1, 3, 3), "{s:?}");
    for &k in &keys[..3] {
        assert!(cache.contains(k));
    }
    for &k in &keys[3..8] {
        assert!(!cache.contains(k));
    }
    // Touch the first so the second is the least recently used; lock the third.
    assert!(cache.get(keys[0]).is_some());
    cache.set_locked([keys[2]]);
    cache.request(keys[8], Class::Real, 1.0);
    cache.wait_real(Duration::from_secs(30)).unwrap();
    assert_eq!(cache.stats().evictions, 1);
    assert!(
        !cache.contains(keys[1]),
        "the least recently used page goes"
    );
    assert!(cache.contains(keys[0]) && cache.contains(keys[2]) && cache.contains(keys[8]));
    // Only unlocked pages go: the locked one outlives older ones.
    cache.request(keys[9], Class::Real, 1.0);
    cache.wait_real(Duration::from_secs(30)).unwrap();
    assert!(!cache.contains(keys[0]) && cache.contains(keys[2]));
    drop(cache);

    // One loader, many prefetches queued, then one real request: it is read next, not
    // after the prefetches (only what the loader took while the requests were being queued
    // was read before it; a queue in arrival order would read them all first).
    // (On a loaded machine the loader may read every prefetch before the real request is
    // even queued, which shows nothing: such rounds are tried again.)
    let (real, rest) = keys.split_last().unwrap();
    let mut shown = false;
    for _ in 0..20 {
        let cache = PageCache::new(vec![store.clone()], 1 << 30, 1);
        for &k in rest {
            cache.request(k, Class::Prefetch, 1.0);
        }
        let before = cache.stats().pages_read;
        cache.request(*real, Class::Real, 1.0);
        cache.wait_real(Duration::from_secs(30)).unwrap();
        // Counted when the real page was read: the loader goes on with the prefetches
        // while this thread wakes up (on a loaded machine, dozens of them).
        let read = cache.stats().pages_read_at_last_real;
        assert!(cache.contains(*real));
        if before + 4 >= rest.len() as u64 {
            continue;
        }
        // The one in flight when it was queued and the real one (a queue in arrival order
        // would have read every prefetch first).
        assert!(
            read - before < (rest.len() as u64 - before) / 2,
            "{} pages read from the real request's queueing to its read (with {before} read \
             before it, of {} queued)",
            read - before,
            rest.len()
        );
        shown = true;
        break;
    }
    assert!(
        shown,
        "every prefetch was read before the real request was queued, 20 times"
    );
}

/// A wait that times out reports the loads still out; should one of them fail later, its
/// error belongs to that wait, not to the next one (which had failed with another round's
/// message). Asked for again, the page's error is reported again.
#[test]
fn a_load_error_after_a_timed_out_wait_does_not_fail_the_next_wait() {
    use std::os::unix::fs::FileExt;
    let dir = TempDir::new().unwrap();
    let (store, _) = store_of_pages(dir.path());
    let path = dir.path().join("v.strata");
    let bad = *store
        .index()
        .iter()
        .find(|e| e.has_payload() && e.id.level() == 0)
        .unwrap();
    let good = store
        .index()
        .iter()
        .find(|e| e.has_payload() && e.id != bad.id)
        .unwrap()
        .id
        .0;
    drop(store);
    let f = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&path)
        .unwrap();
    let mut b = [0u8];
    f.read_exact_at(&mut b, bad.offset + 7).unwrap();
    f.write_all_at(&[b[0] ^ 0x40], bad.offset + 7).unwrap();
    let store = Arc::new(PageStore::open(&path).unwrap());
    let mut timed_out = false;
    for _ in 0..50 {
        let cache = PageCache::new(vec![store.clone()], 1 << 30, 1);
        cache.request(bad.id.0, Class::Real, 1.0);
        match cache.wait_real(Duration::ZERO) {
            Err(e) if e.contains("did not finish") => {}
            _ => continue, // the load finished first: try again
        }
        timed_out = true;
        cache.request(good, Class::Real, 1.0);
        cache.wait_real(Duration::from_secs(60)).unwrap();
        assert!(cache.get(good).is_some());
        // Asked for again: its own error.
        cache.request(bad.id.0, Class::Real, 1.0);
        let e = cache.wait_real(Duration::from_secs(60)).unwrap_err();
        assert!(e.contains("checksum") || e.contains("crc"), "{e}");
        break;
    }
    assert!(
        timed_out,
        "every load finished before a zero wait: the test shows nothing"
    );
    // Asked for again while its load is still out (the next round wants it too): the wait
    // for it reports its error (it had been dropped with the timed-out wait's).
    let mut again = false;
    for _ in 0..50 {
        let cache = PageCache::new(vec![store.clone()], 1 << 30, 1);
        cache.request(bad.id.0, Class::Real, 1.0);
        match cache.wait_real(Duration::ZERO) {
            Err(e) if e.contains("did not finish") => {}
            _ => continue,
        }
        again = true;
        cache.request(bad.id.0, Class::Real, 1.0);
        let e = cache.wait_real(Duration::from_secs(60)).unwrap_err();
        assert!(e.contains("checksum") || e.contains("crc"), "{e}");
        break;
    }
    assert!(
        again,
        "every load finished before a zero wait: the test shows nothing"
    );
}
