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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_budget_changes_the_allocator() {
        assert!(!return_freed_buffers(None));
        #[cfg(all(target_os = "linux", target_env = "gnu"))]
        assert!(return_freed_buffers(Some(1 << 30)));
    }
}
