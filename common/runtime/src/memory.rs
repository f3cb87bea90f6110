//! How a process gives memory back to the system when the graph sets a memory budget.
//!
//! glibc's malloc serves blocks of 128 KiB and more by mmap, but raises that threshold each
//! time such a block is freed, up to 32 MiB. A run frees tile-sized (4 MiB) and chunk-sized
//! (1 MiB) buffers all the time, so after the first tiles nearly every buffer comes from the
//! per-thread arenas instead, and an arena keeps what it once held: the process stays at its
//! high-water mark of every phase at once. A fixed threshold of 1 MiB (which also switches the
//! raising off) sends every buffer of 1 MiB or more to mmap and back to the system on free.
//! Measured (`python3 scripts/bench_memory.py --rows 6 --mode run --set
//! graph.memory_budget_gb=0.5`, one machine, back to back, load ~2): peak 802 MB with the
//! default, 510 MB with 1 MiB, for 16.4 s vs 21.3 s wall (page faults on every fresh buffer).
//! So it is done only under a budget, where the user asked for memory over speed.
//!
//! [`MemoryPlan`]: how the budget is shared among the nodes, and where spill files go.

use std::path::PathBuf;

/// Blocks of this size or more are mapped and unmapped on their own under a budget.
pub const MMAP_THRESHOLD_UNDER_BUDGET: usize = 1 << 20;

/// Under a memory budget, make malloc return large freed blocks to the system (see the module
/// doc). Returns whether the allocator took the setting (false off glibc, or without a budget).
pub fn return_freed_buffers(budget_bytes: Option<u64>) -> bool {
    if budget_bytes.is_none() {
        return false;
    }
    set_mmap_threshold(MMAP_THRESHOLD_UNDER_BUDGET)
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn set_mmap_threshold(bytes: usize) -> bool {
    let Ok(bytes) = libc::c_int::try_from(bytes) else {
        return false;
    };
    // SAFETY: mallopt only changes allocator parameters; it is safe to call at any time.
    unsafe { libc::mallopt(libc::M_MMAP_THRESHOLD, bytes) == 1 }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn set_mmap_threshold(_bytes: usize) -> bool {
    false
}

/// Under a memory budget, hand the free pages of every malloc arena back to the system now
/// (glibc's `malloc_trim(0)`). The mmap threshold above returns large buffers on free, but the
/// smaller blocks a phase frees stay resident in the arenas of the threads that used them, and
/// an arena shrinks only from its top, so a finished node's arenas would stay under the next
/// node's peak (measured on the 6 x 6 demo: docs/benchmarks.md, "The 6 x 6 within 1.5 x the
/// budget"). Called when a node of `run` finishes ([`crate::inproc`]). Returns whether memory was
/// released (false off glibc, or without a budget).
pub fn release_freed_pages(budget_bytes: Option<u64>) -> bool {
    if budget_bytes.is_none() {
        return false;
    }
    trim_arenas()
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn trim_arenas() -> bool {
    // SAFETY: malloc_trim only returns free memory of the allocator's own arenas to the
    // system; it is thread-safe and may be called at any time.
    unsafe { libc::malloc_trim(0) == 1 }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn trim_arenas() -> bool {
    false
}

/// How a run's memory is shared among its nodes, decided in one place: the budget
/// (`[graph] memory_budget_gb`), each node's share of it, the default without one, and the
/// folder every spill file goes to. The launcher resolves it once per run (MemAvailable is read
/// then, so every node plans with the same figure), and it travels to each node inside its
/// [`crate::graph::NodeContext`] (`memory` in graph.resolved.json); nodes take their share by
/// name, so no node parses /proc or divides the budget itself.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct MemoryPlan {
    /// `[graph] memory_budget_gb` in bytes; `None`: no budget.
    pub budget_bytes: Option<u64>,
    /// MemAvailable of /proc/meminfo when the plan was made; `None` where it cannot be read.
    pub available_bytes: Option<u64>,
    /// Where spill files go (unnamed, gone at exit): the out dir, beside the outputs (the
    /// system temp folder may be a RAM disk).
    pub spill_dir: PathBuf,
}

impl MemoryPlan {
    /// The part of the budget one node's chunk store may hold in memory: a quarter each for
    /// the fusion's panorama chunks and the wavelet's live mirror; the rest is for the final
    /// panorama frame (4 bytes per pixel) and the other nodes.
    pub const CHUNK_SHARE_OF_BUDGET: u64 = 4;
    /// Without a budget, the fusion's chunks may hold an eighth of MemAvailable (2.75 GB on
    /// a machine with 22 GB free: a 20 x 20 scan of 1024 px fields, 303 Mpx, keeps its 2.4 GB
    /// of chunks in memory, larger scans spill), so a scan of any size runs without a setting.
    pub const CHUNK_SHARE_OF_AVAILABLE: u64 = 8;

    /// The plan for a run: the budget, MemAvailable read now, the spill folder.
    pub fn resolve(budget_bytes: Option<u64>, spill_dir: PathBuf) -> Self {
        let available_bytes = std::fs::read_to_string("/proc/meminfo")
            .ok()
            .and_then(|t| mem_available_bytes(&t));
        Self {
            budget_bytes,
            available_bytes,
            spill_dir,
        }
    }

    /// A plan without a budget and without MemAvailable (no limit anywhere): for tests and
    /// tools that build a node's context by hand.
    pub fn unlimited(spill_dir: PathBuf) -> Self {
        Self {
            budget_bytes: None,
            available_bytes: None,
            spill_dir,
        }
    }

    /// Bytes the fusion's panorama chunks may keep in memory: a quarter of the budget, or
    /// without one an eighth of MemAvailable; `None`: no limit (neither is known).
    pub fn panorama_chunks_bytes(&self) -> Option<u64> {
        match self.budget_bytes {
            Some(b) => Some(b / Self::CHUNK_SHARE_OF_BUDGET),
            None => self
                .available_bytes
                .map(|a| a / Self::CHUNK_SHARE_OF_AVAILABLE),
        }
    }

    /// Bytes the wavelet's live mirror of the panorama may keep in memory: a quarter of the
    /// budget; `None` (no limit) without one.
    pub fn live_mirror_bytes(&self) -> Option<u64> {
        self.budget_bytes.map(|b| b / Self::CHUNK_SHARE_OF_BUDGET)
    }

    /// Each node's share of the budget, for the nodes of a graph by kind (`kinds`, in the
    /// graph's order), bytes: what its process may hold at its peak under `launch`, the figure
    /// run.json's `peak_rss` sets each node's peak against. [`node_shares`]; `None` without a
    /// budget.
    pub fn node_shares_bytes(&self, kinds: &[&str]) -> Option<Vec<u64>> {
        self.budget_bytes.map(|b| node_shares(b, kinds))
    }
}

/// Node kinds that hold a planned share of their own: the fusion (its panorama chunks), the
/// wavelet (its live mirror) and the mesher (the tolerance search, its insertion order spilled
/// between checkpoints), a quarter of the budget each ([`MemoryPlan::CHUNK_SHARE_OF_BUDGET`]).
pub const NODES_WITH_A_QUARTER: [&str; 3] = ["fusion", "wavelet", "mesher"];

/// The budget shared among the nodes of a graph (`kinds`): a quarter to each fusion, wavelet
/// and mesher node ([`NODES_WITH_A_QUARTER`]; a graph with two of one kind splits its
/// quarter), and what is left split evenly among the other nodes (the source, the matcher, the
/// recorder, ...). The shares add up to the budget (less rounding) whatever the graph holds.
pub fn node_shares(budget_bytes: u64, kinds: &[&str]) -> Vec<u64> {
    let quarter = budget_bytes / MemoryPlan::CHUNK_SHARE_OF_BUDGET;
    let count = |k: &str| kinds.iter().filter(|&&x| x == k).count() as u64;
    let planned: Vec<&str> = NODES_WITH_A_QUARTER
        .into_iter()
        .filter(|k| count(k) > 0)
        .collect();
    let others = kinds.iter().filter(|k| !planned.contains(k)).count() as u64;
    let left = budget_bytes.saturating_sub(quarter * planned.len() as u64);
    kinds
        .iter()
        .map(|k| {
            if planned.contains(k) {
                quarter / count(k)
            } else {
                left / others.max(1)
            }
        })
        .collect()
}

/// MemAvailable of a /proc/meminfo text, in bytes.
pub fn mem_available_bytes(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let mut words = line.split_whitespace().skip(1);
    let kb: u64 = words.next()?.parse().ok()?;
    (words.next() == Some("kB")).then_some(kb.checked_mul(1024)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_budget_changes_the_allocator() {
        assert!(!return_freed_buffers(None));
        assert!(!release_freed_pages(None));
        #[cfg(all(target_os = "linux", target_env = "gnu"))]
        assert!(return_freed_buffers(Some(1 << 30)));
    }

    #[test]
    fn mem_available_is_read_from_meminfo() {
        let text = "MemTotal:       24534712 kB\nMemFree:         1204720 kB\nMemAvailable:   22011236 kB\n";
        assert_eq!(mem_available_bytes(text), Some(22_011_236 * 1024));
        assert_eq!(mem_available_bytes("MemTotal: 1 kB\n"), None);
        assert_eq!(mem_available_bytes("MemAvailable: lots\n"), None);
        assert_eq!(mem_available_bytes("MemAvailable: 12 MB\n"), None);
    }

    #[test]
    fn each_node_takes_its_share_of_the_plan() {
        let plan = |budget, available| MemoryPlan {
            budget_bytes: budget,
            available_bytes: available,
            spill_dir: "out".into(),
        };
        let p = plan(Some(100_000_000), Some(8_000_000_000));
        assert_eq!(p.panorama_chunks_bytes(), Some(25_000_000));
        assert_eq!(p.live_mirror_bytes(), Some(25_000_000));
        let p = plan(None, Some(8_000_000_000));
        assert_eq!(p.panorama_chunks_bytes(), Some(1_000_000_000));
        assert_eq!(p.live_mirror_bytes(), None);
        assert_eq!(plan(None, None).panorama_chunks_bytes(), None);
        let kinds = [
            "replay", "matcher", "fusion", "wavelet", "mesher", "recorder",
        ];
        assert_eq!(p.node_shares_bytes(&kinds), None);
        let p = plan(Some(1_200_000_000), None);
        let shares = p.node_shares_bytes(&kinds).unwrap();
        assert_eq!(
            shares,
            [
                100_000_000,
                100_000_000,
                300_000_000,
                300_000_000,
                300_000_000,
                100_000_000
            ]
        );
        assert_eq!(shares.iter().sum::<u64>(), 1_200_000_000);
        // Without a mesher its quarter goes to the others; two fusions split theirs.
        let shares = node_shares(1_200_000_000, &["replay", "fusion", "fusion"]);
        assert_eq!(shares, [900_000_000, 150_000_000, 150_000_000]);
        let p = MemoryPlan::resolve(Some(7), "out".into());
        assert_eq!((p.budget_bytes, p.spill_dir), (Some(7), "out".into()));
    }
}
