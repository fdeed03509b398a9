//! The page cache's loader threads: a real request for a page whose prefetch is already
//! loading queues it again, so two loaders can read the same page at once; the request must
//! be counted done exactly once (the race once underflowed the outstanding count and
//! poisoned the cache, seen in a distributed sequence test).

use std::sync::Arc;
use std::time::Duration;
use strata_common::geo::Affine3;
use strata_common::store::PageStore;
use strata_tests::scenes::volume_store;
use strata_worker::cache::{Class, PageCache};
use tempfile::TempDir;

#[test]
fn a_real_request_for_a_page_being_prefetched_is_counted_once() {
    let dir = TempDir::new().unwrap();
    let n = 96u64;
    let data: Vec<f32> = (0..n * n * n).map(|i| (i % 251) as f32).collect();
    let p = volume_store(dir.path(), "v", [n, n, n], data, Affine3::IDENTITY, 32);
    let store = Arc::new(PageStore::open(&p).unwrap());
    let keys: Vec<u64> = store.index().iter().map(|e| e.id.0).collect();
    assert!(keys.len() > 20);
    for _ in 0..100 {
        let cache = PageCache::new(vec![store.clone()], 1 << 30, 2);
        for &k in &keys {
            cache.request(k, Class::Prefetch, 1.0);
        }
        // Upgrade every page while the loaders are busy with the prefetches.
        for &k in &keys {
            cache.request(k, Class::Real, 2.0);
        }
        cache.wait_real(Duration::from_secs(60)).unwrap();
        for &k in &keys {
            assert!(cache.get(k).is_some(), "page {k:#x} not loaded");
        }
    }
}
