//! CPU affinity: which CPUs a process may run on, and how a local run binds its worker
//! processes to their own CPUs (`cluster.pin_workers`), as MPI launchers bind ranks.
//!
//! Unbound, the scheduler moves a worker's render threads over every core of the machine,
//! across last-level caches, and two workers' threads can meet on one core while another
//! idles. Bound, worker `i` runs on its own block of CPUs. The blocks are cut from this
//! process's allowed CPUs in [`topology_order`]: by package, then last-level cache, then
//! core, so that a block stays within one cache and takes a core's hardware threads
//! together.

/// The CPUs the calling thread may run on, ascending (`sched_getaffinity`); `None` where
/// the system will not say.
pub fn allowed() -> Option<Vec<usize>> {
    // SAFETY: `cpu_set_t` is plain data; `sched_getaffinity` fills the set it is given.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        if libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set) != 0 {
            return None;
        }
        let cpus: Vec<usize> = (0..libc::CPU_SETSIZE as usize)
            .filter(|&c| libc::CPU_ISSET(c, &set))
            .collect();
        (!cpus.is_empty()).then_some(cpus)
    }
}

/// A CPU set for [`CpuSet::bind`], built ahead of a `fork` (building it allocates nothing, but
/// a `pre_exec` closure should do as little as it can).
#[derive(Clone, Copy)]
pub struct CpuSet(libc::cpu_set_t);

impl CpuSet {
    /// The set of `cpus` (those past `CPU_SETSIZE` are left out).
    pub fn new(cpus: &[usize]) -> CpuSet {
        // SAFETY: an all-zero `cpu_set_t` is the empty set; `CPU_SET` writes within it
        // for CPUs below `CPU_SETSIZE`.
        let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
        for &c in cpus.iter().filter(|&&c| c < libc::CPU_SETSIZE as usize) {
            unsafe { libc::CPU_SET(c, &mut set) };
        }
        CpuSet(set)
    }

    /// Binds the calling thread (in a freshly forked child: the process to be, whose
    /// threads inherit it) to this set.
    pub fn bind(&self) -> std::io::Result<()> {
        // SAFETY: the set outlives the call; 0 is the calling thread.
        let r =
            unsafe { libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &self.0) };
        if r != 0 {
            return Err(std::io::Error::last_os_error());
        }
        Ok(())
    }
}

/// `cpus` as Linux writes CPU lists (`0-3,8,10-11`); ascending input.
pub fn format_list(cpus: &[usize]) -> String {
    let mut out = String::new();
    let mut i = 0;
    while i < cpus.len() {
        let mut j = i;
        while j + 1 < cpus.len() && cpus[j + 1] == cpus[j] + 1 {
            j += 1;
        }
        if !out.is_empty() {
            out.push(',');
        }
        match j - i {
            0 => out.push_str(&cpus[i].to_string()),
            _ => out.push_str(&format!("{}-{}", cpus[i], cpus[j])),
        }
        i = j + 1;
    }
    out
}

/// Where one CPU sits: its package, its last-level cache and its core (hardware threads of
/// one core share all three).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Place {
    /// Socket (`physical_package_id`).
    pub package: u32,
    /// Last-level cache (the id of the highest cache index that has one).
    pub cache: u32,
    /// Core within the package (`core_id`).
    pub core: u32,
}

/// The place of CPU `cpu` from `/sys/devices/system/cpu`; zeros for what it does not
/// say (then the order falls back to the CPU numbers).
pub fn place_of(cpu: usize) -> Place {
    let base = format!("/sys/devices/system/cpu/cpu{cpu}");
    let read = |p: &str| -> Option<u32> {
        std::fs::read_to_string(format!("{base}/{p}"))
            .ok()?
            .trim()
            .parse()
            .ok()
    };
    // The last-level cache is the highest `cache/indexN` with an id.
    let cache = (0..8)
        .rev()
        .find_map(|i| read(&format!("cache/index{i}/id")))
        .unwrap_or(0);
    Place {
        package: read("topology/physical_package_id").unwrap_or(0),
        cache,
        core: read("topology/core_id").unwrap_or(0),
    }
}

/// `cpus` ordered by place (package, last-level cache, core), then by number: contiguous
/// runs of the result share caches, and a core's hardware threads are neighbours.
pub fn topology_order(cpus: &[usize], place: impl Fn(usize) -> Place) -> Vec<usize> {
    let mut keyed: Vec<(Place, usize)> = cpus.iter().map(|&c| (place(c), c)).collect();
    keyed.sort();
    keyed.into_iter().map(|(_, c)| c).collect()
}

/// The CPUs of worker `slot` of `workers`, each wanting `threads` of them, from `order`
/// (see [`topology_order`]): `order` is cut into `workers` even shares and each worker
/// takes the first `min(threads, share)` CPUs of its own, so workers spread over the
/// machine's cores and caches (not packed onto the first ones, where a core's second
/// hardware thread would go to the next worker) and never share a CPU while there are
/// enough; with more workers than CPUs, one CPU each, round robin (shared). The second
/// value is whether this worker's CPUs are shared with another worker's.
pub fn block_for(
    order: &[usize],
    workers: usize,
    threads: usize,
    slot: usize,
) -> (Vec<usize>, bool) {
    let n = order.len();
    if n == 0 {
        return (Vec::new(), false);
    }
    let workers = workers.max(1);
    if workers > n {
        return (vec![order[slot % n]], true);
    }
    let share = n / workers;
    let size = threads.clamp(1, share);
    let start = (slot % workers) * share;
    (order[start..start + size].to_vec(), false)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_lists_read_as_linux_writes_them() {
        assert_eq!(format_list(&[]), "");
        assert_eq!(format_list(&[3]), "3");
        assert_eq!(format_list(&[0, 1, 2, 3, 8, 10, 11]), "0-3,8,10-11");
        assert_eq!(format_list(&[0, 2, 4]), "0,2,4");
    }

    /// Two packages, each of two caches of two cores of two hardware threads, numbered as
    /// Linux numbers them on such machines: the second threads of all cores come after the
    /// first ones (cpu c and c + 16 are siblings).
    fn place(c: usize) -> Place {
        let first = c % 16;
        Place {
            package: (first / 8) as u32,
            cache: (first / 4) as u32,
            core: (first % 8) as u32,
        }
    }

    #[test]
    fn blocks_keep_a_core_and_a_cache_together() {
        let all: Vec<usize> = (0..32).collect();
        let order = topology_order(&all, place);
        // A core's two threads are neighbours, a cache's four cores follow each other.
        assert_eq!(&order[..8], &[0, 16, 1, 17, 2, 18, 3, 19]);
        // Sixteen 2-thread workers: each on both threads of one core, disjoint.
        let blocks: Vec<Vec<usize>> = (0..16).map(|s| block_for(&order, 16, 2, s).0).collect();
        assert_eq!(blocks[0], vec![0, 16]);
        assert_eq!(blocks[1], vec![1, 17]);
        assert_eq!(blocks[15], vec![15, 31]);
        let mut seen: Vec<usize> = blocks.concat();
        seen.sort();
        seen.dedup();
        assert_eq!(seen.len(), 32);
        // Eight: spread one core apart, each on one core's two threads (never a second
        // worker on a core's other thread).
        let blocks: Vec<Vec<usize>> = (0..8).map(|s| block_for(&order, 8, 2, s).0).collect();
        assert_eq!(blocks[0], vec![0, 16]);
        assert_eq!(blocks[1], vec![2, 18]);
        assert_eq!(blocks[7], vec![14, 30]);
        // Two 1-thread workers: on different cores in different packages.
        let (a, b) = (block_for(&order, 2, 1, 0).0, block_for(&order, 2, 1, 1).0);
        assert_eq!((a.clone(), b.clone()), (vec![0], vec![8]));
        assert_ne!(place(a[0]).package, place(b[0]).package);
        // Four 4-thread workers: two whole cores each, within one cache.
        for s in 0..4 {
            let (b, shared) = block_for(&order, 4, 4, s);
            assert!(!shared);
            let caches: std::collections::BTreeSet<u32> =
                b.iter().map(|&c| place(c).cache).collect();
            assert_eq!(caches.len(), 1, "block {b:?} spans caches");
        }
    }

    #[test]
    fn blocks_shrink_to_fit_and_share_only_past_one_cpu_each() {
        let order: Vec<usize> = (0..4).collect();
        // More threads than fit: an even share each.
        assert_eq!(block_for(&order, 2, 8, 0), (vec![0, 1], false));
        assert_eq!(block_for(&order, 2, 8, 1), (vec![2, 3], false));
        // Fewer threads than a share: exactly `threads` each, from the front of its share.
        assert_eq!(block_for(&order, 2, 1, 1), (vec![2], false));
        // Three workers on four CPUs: one each, the last CPU unused.
        assert_eq!(block_for(&order, 3, 2, 2), (vec![2], false));
        // More workers than CPUs: one CPU each, round robin, shared.
        assert_eq!(block_for(&order, 8, 1, 5), (vec![1], true));
        // A replacement takes its slot's block again.
        assert_eq!(block_for(&order, 2, 2, 3), block_for(&order, 2, 2, 1));
        assert_eq!(block_for(&[], 2, 2, 0), (vec![], false));
    }

    #[test]
    fn this_process_has_cpus_and_a_list_of_them() {
        let cpus = allowed().expect("sched_getaffinity answers on Linux");
        assert!(!cpus.is_empty());
        assert!(cpus.windows(2).all(|w| w[0] < w[1]));
        let order = topology_order(&cpus, place_of);
        let mut sorted = order.clone();
        sorted.sort();
        assert_eq!(
            sorted, cpus,
            "the order is a permutation of the allowed CPUs"
        );
    }
}
