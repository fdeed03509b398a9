//! The host page cache: decoded pages of every data set of a worker under one byte budget.
//!
//! * Replacement is least-recently-used; the pages of the loading round in progress are
//!   *locked* (never evicted) until they are copied into the atlas, which keeps its own copy.
//!   The engine locks no more of them than the budget holds (at least one page), so the
//!   budget holds at every moment (`CacheStats::peak_bytes`) unless it is below one page.
//! * Loader threads read and decode pages from a priority queue. Real requests (pages rays
//!   asked for) always outrank prefetch; within a class, higher priority first.
//! * Prefetched pages only fill free budget: they never evict anything.
//!
//! Pages are keyed by their [`PageId`] with the data-set field set to the worker's data-set
//! number, so one key space covers all stores.

use std::collections::{BTreeMap, BinaryHeap, HashMap, HashSet};
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use strata_common::ids::PageId;
use strata_common::store::PageStore;

/// Decoded samples of one page (border included; NaN = no data / hole).
pub type PageData = Arc<Vec<f32>>;

/// Request classes, in increasing precedence.
#[derive(Copy, Clone, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Class {
    /// Speculative: only fills free budget.
    Prefetch = 0,
    /// A page rays asked for (or an ancestor of one).
    Real = 1,
}

/// Counters of a cache.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct CacheStats {
    /// Real requests (pages the atlas lacked) whose page the cache held.
    pub hits: u64,
    /// Real requests whose page had to be read.
    pub misses: u64,
    /// Pages evicted.
    pub evictions: u64,
    /// Pages read from disk.
    pub pages_read: u64,
    /// Stored bytes read from disk.
    pub bytes_read: u64,
    /// Prefetched pages dropped for lack of free budget.
    pub prefetch_dropped: u64,
    /// `pages_read` just after the last real request's page was read: what it waited
    /// behind, whatever the loaders read after it.
    pub pages_read_at_last_real: u64,
    /// The most decoded bytes held at once.
    pub peak_bytes: u64,
}

#[derive(PartialEq)]
struct Queued {
    class: Class,
    priority: f32,
    seq: u64,
    key: u64,
}
impl Eq for Queued {}
impl Ord for Queued {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        self.class
            .cmp(&o.class)
            .then(self.priority.total_cmp(&o.priority))
            // earlier requests first among equals
            .then(o.seq.cmp(&self.seq))
    }
}
impl PartialOrd for Queued {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}

struct Entry {
    data: PageData,
    tick: u64,
}

#[derive(Default)]
struct State {
    map: HashMap<u64, Entry>,
    lru: BTreeMap<u64, u64>, // tick -> key
    locked: HashSet<u64>,
    /// Queued or being loaded, with the best class asked for.
    pending: HashMap<u64, Class>,
    in_flight: usize,
    real_outstanding: usize,
    heap: BinaryHeap<Queued>,
    bytes: u64,
    tick: u64,
    seq: u64,
    stats: CacheStats,
    errors: Vec<String>,
    /// Real requests outstanding when a wait for them timed out: that wait reported them
    /// (as the timeout), so their errors, should they fail later, are not a later round's;
    /// asked for again, a key counts anew.
    abandoned: HashSet<u64>,
    shutdown: bool,
}

struct Shared {
    state: Mutex<State>,
    /// Wakes loaders (work queued) and waiters (work finished).
    work: Condvar,
    done: Condvar,
    stores: Vec<Arc<PageStore>>,
    budget: u64,
    /// Loader threads running (one that panicked outside a page's read has stopped).
    loaders: std::sync::atomic::AtomicUsize,
}

/// Counts its loader out of [`Shared::loaders`] when the loader ends, by return or panic.
struct LoaderAlive<'a>(&'a Shared);

impl Drop for LoaderAlive<'_> {
    fn drop(&mut self) {
        self.0
            .loaders
            .fetch_sub(1, std::sync::atomic::Ordering::SeqCst);
    }
}

/// The cache and its loader threads.
pub struct PageCache {
    shared: Arc<Shared>,
    threads: Vec<JoinHandle<()>>,
}

fn page_bytes(store: &PageStore) -> u64 {
    (store.pyramid().page_samples() * 4) as u64
}

impl PageCache {
    /// A cache over `stores` (data set `i` is `stores[i]`) with `budget` bytes of decoded
    /// pages and `threads` loader threads.
    pub fn new(stores: Vec<Arc<PageStore>>, budget: u64, threads: usize) -> Self {
        let shared = Arc::new(Shared {
            state: Mutex::new(State::default()),
            work: Condvar::new(),
            done: Condvar::new(),
            stores,
            budget,
            loaders: std::sync::atomic::AtomicUsize::new(threads.max(1)),
        });
        let threads = (0..threads.max(1))
            .map(|i| {
                let s = shared.clone();
                std::thread::Builder::new()
                    .name(format!("page-loader-{i}"))
                    .spawn(move || loader(s))
                    .expect("spawning a loader thread")
            })
            .collect();
        PageCache { shared, threads }
    }

    /// The budget in bytes.
    pub fn budget(&self) -> u64 {
        self.shared.budget
    }

    /// The bytes page `key` takes here once decoded (what it counts against the budget;
    /// 0 for an unknown data set).
    pub fn page_bytes(&self, key: u64) -> u64 {
        page_bytes_of(&self.shared.stores, key)
    }

    /// Loader threads still running (all of them until the cache drops, unless one panicked
    /// outside a page's read: a bug this lets tests see).
    #[doc(hidden)]
    pub fn loaders_running(&self) -> usize {
        self.shared
            .loaders
            .load(std::sync::atomic::Ordering::SeqCst)
    }

    /// Decoded bytes held now.
    pub fn bytes(&self) -> u64 {
        self.shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .bytes
    }

    /// Counters so far.
    pub fn stats(&self) -> CacheStats {
        self.shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .stats
    }

    /// Looks a page up and refreshes its age. (Hits and misses are counted where pages are
    /// asked for, [`request`](Self::request): a lookup after the wait for its load would
    /// always hit.)
    pub fn get(&self, key: u64) -> Option<PageData> {
        let mut st = self
            .shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        st.tick += 1;
        let tick = st.tick;
        let State { map, lru, .. } = &mut *st;
        let e = map.get_mut(&key)?;
        lru.remove(&e.tick);
        e.tick = tick;
        lru.insert(tick, key);
        Some(e.data.clone())
    }

    /// Whether the page is held (no counters touched).
    pub fn contains(&self, key: u64) -> bool {
        self.shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .map
            .contains_key(&key)
    }

    /// Queues a page for loading unless it is held or already queued at this class or above.
    pub fn request(&self, key: u64, class: Class, priority: f32) {
        let mut st = self
            .shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if st.map.contains_key(&key) {
            if class == Class::Real {
                st.stats.hits += 1;
            }
            return;
        }
        // A real request counts its page's error anew, even one still loading for a wait
        // that timed out (before the early return below, which it may take).
        if class == Class::Real {
            st.abandoned.remove(&key);
        }
        if let Some(&c) = st.pending.get(&key) {
            if c >= class {
                return;
            }
        }
        if class == Class::Real && st.pending.get(&key) != Some(&Class::Real) {
            st.real_outstanding += 1;
            st.stats.misses += 1;
        }
        st.pending.insert(key, class);
        st.seq += 1;
        let seq = st.seq;
        st.heap.push(Queued {
            class,
            priority,
            seq,
            key,
        });
        drop(st);
        self.shared.work.notify_one();
    }

    /// Replaces the set of locked pages (never evicted while locked).
    pub fn set_locked(&self, keys: impl IntoIterator<Item = u64>) {
        let mut st = self
            .shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        st.locked = keys.into_iter().collect();
    }

    /// Drops queued prefetch requests (a new frame's feedback supersedes them).
    pub fn cancel_prefetch(&self) {
        let mut st = self
            .shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let heap = std::mem::take(&mut st.heap);
        let mut keep = BinaryHeap::new();
        for q in heap {
            if q.class == Class::Prefetch && st.pending.get(&q.key) == Some(&Class::Prefetch) {
                st.pending.remove(&q.key);
            } else {
                keep.push(q);
            }
        }
        st.heap = keep;
    }

    /// Waits until no real request is queued or being loaded. Returns the load errors seen
    /// since the last call (a page that fails to load is reported, not retried forever).
    pub fn wait_real(&self, timeout: Duration) -> Result<(), String> {
        let deadline = Instant::now() + timeout;
        let mut st = self
            .shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        while st.real_outstanding > 0 {
            let now = Instant::now();
            if now >= deadline {
                // This wait reports the loads still out, and every error so far: none of
                // them is to fail a later wait.
                let out: Vec<u64> = st
                    .pending
                    .iter()
                    .filter(|&(_, &c)| c == Class::Real)
                    .map(|(&k, _)| k)
                    .collect();
                st.abandoned.extend(out);
                let earlier = std::mem::take(&mut st.errors);
                let mut msg = format!(
                    "page loads did not finish within {:?} ({} outstanding)",
                    timeout, st.real_outstanding
                );
                if !earlier.is_empty() {
                    msg = format!("{msg}; {}", earlier.join("; "));
                }
                return Err(msg);
            }
            st = self
                .shared
                .done
                .wait_timeout(st, deadline - now)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
        if st.errors.is_empty() {
            Ok(())
        } else {
            Err(std::mem::take(&mut st.errors).join("; "))
        }
    }

    /// Loads a page on the calling thread (used for the pinned roots), inserting it.
    pub fn load_now(&self, key: u64) -> anyhow::Result<PageData> {
        if let Some(d) = self.get(key) {
            self.shared
                .state
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .stats
                .hits += 1;
            return Ok(d);
        }
        let (data, stored) = read(&self.shared.stores, key)?;
        let mut st = self
            .shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        st.stats.pages_read += 1;
        st.stats.bytes_read += stored;
        st.stats.misses += 1;
        insert(&self.shared, &mut st, key, data.clone(), Class::Real);
        Ok(data)
    }
}

impl Drop for PageCache {
    fn drop(&mut self) {
        self.shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .shutdown = true;
        self.shared.work.notify_all();
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

fn read(stores: &[Arc<PageStore>], key: u64) -> anyhow::Result<(PageData, u64)> {
    let id = PageId(key);
    let store = stores
        .get(id.dataset() as usize)
        .ok_or_else(|| anyhow::anyhow!("page {key:#x} names an unknown data set"))?;
    let local = id.with_dataset(0);
    let stored = store.entry(local).map(|e| e.stored_len as u64).unwrap_or(0);
    let mut buf = vec![0.0f32; store.pyramid().page_samples()];
    store.read_page_into(local, &mut buf)?;
    Ok((Arc::new(buf), stored))
}

/// Inserts, evicting unlocked least-recently-used pages to stay within budget. Prefetched
/// pages are dropped instead of evicting anything.
fn insert(shared: &Shared, st: &mut State, key: u64, data: PageData, class: Class) {
    let size = data.len() as u64 * 4;
    if st.map.contains_key(&key) {
        return;
    }
    if class == Class::Prefetch && st.bytes + size > shared.budget {
        st.stats.prefetch_dropped += 1;
        return;
    }
    if st.bytes + size > shared.budget {
        // Oldest first; locked pages are skipped (collected, then removed).
        let mut victims = Vec::new();
        let mut freed = 0;
        for (&tick, &k) in st.lru.iter() {
            if st.bytes + size - freed <= shared.budget {
                break;
            }
            if st.locked.contains(&k) {
                continue;
            }
            victims.push((tick, k));
            freed += st.map[&k].data.len() as u64 * 4;
        }
        for (tick, k) in victims {
            st.lru.remove(&tick);
            let e = st.map.remove(&k).unwrap();
            st.bytes -= e.data.len() as u64 * 4;
            st.stats.evictions += 1;
        }
        // If locked pages fill the budget the page is still inserted: the cut must be
        // resident to make progress. The engine locks no more than the budget holds (at
        // least one page), so this overshoots only for a budget below one page.
    }
    st.tick += 1;
    let tick = st.tick;
    st.lru.insert(tick, key);
    st.bytes += size;
    st.stats.peak_bytes = st.stats.peak_bytes.max(st.bytes);
    st.map.insert(key, Entry { data, tick });
}

fn loader(shared: Arc<Shared>) {
    let _alive = LoaderAlive(&shared);
    loop {
        let job = {
            let mut st = shared.state.lock().unwrap_or_else(PoisonError::into_inner);
            loop {
                if st.shutdown {
                    return;
                }
                if let Some(q) = st.heap.pop() {
                    // Skip stale heap entries (re-queued at a higher class, or cancelled).
                    match st.pending.get(&q.key) {
                        Some(&c) if c == q.class => {
                            // A prefetch the full cache would drop is not read at all: once
                            // the cache has filled, only real loads make room.
                            if q.class == Class::Prefetch
                                && st.bytes + page_bytes_of(&shared.stores, q.key) > shared.budget
                            {
                                st.pending.remove(&q.key);
                                st.stats.prefetch_dropped += 1;
                                continue;
                            }
                            st.in_flight += 1;
                            break q;
                        }
                        _ => continue,
                    }
                }
                st = shared.work.wait(st).unwrap_or_else(PoisonError::into_inner);
            }
        };
        // A panic while decoding (a bug; bad files are errors) is this page's error: the
        // request is still counted done and the loader thread lives on, so the frame fails
        // with the cause instead of waiting out its timeout.
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            read(&shared.stores, job.key)
        }))
        .unwrap_or_else(|p| {
            let what = p
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| p.downcast_ref::<String>().cloned())
                .unwrap_or_default();
            Err(anyhow::anyhow!(
                "reading page {:#x} panicked: {what}",
                job.key
            ))
        });
        let mut st = shared.state.lock().unwrap_or_else(PoisonError::into_inner);
        st.in_flight -= 1;
        // The pending entry is what a real request was counted against. Two jobs for one
        // page can be in flight (a prefetch already loading when a real request queues it
        // again); the first to finish takes the entry, and the other finds none and must
        // not count the request done a second time.
        let counted = st.pending.remove(&job.key);
        let real = counted == Some(Class::Real);
        match result {
            Ok((data, stored)) => {
                st.stats.pages_read += 1;
                st.stats.bytes_read += stored;
                if real {
                    st.stats.pages_read_at_last_real = st.stats.pages_read;
                }
                insert(
                    &shared,
                    &mut st,
                    job.key,
                    data,
                    counted.unwrap_or(job.class),
                );
            }
            Err(e) => {
                if real && !st.abandoned.contains(&job.key) {
                    st.errors.push(format!("{e:#}"));
                }
            }
        }
        if real {
            st.abandoned.remove(&job.key);
            st.real_outstanding -= 1;
        }
        drop(st);
        shared.done.notify_all();
    }
}

/// Bytes of one decoded page of the store page `key` belongs to (0 for an unknown data set:
/// its read fails and reports it).
fn page_bytes_of(stores: &[Arc<PageStore>], key: u64) -> u64 {
    stores
        .get(PageId(key).dataset() as usize)
        .map_or(0, |s| page_bytes(s))
}

/// Bytes of one decoded page of `store`.
pub fn decoded_page_bytes(store: &PageStore) -> u64 {
    page_bytes(store)
}
