//! Liveness from inside long computations.
//!
//! A launched node proves it is alive by a heartbeat that the launcher's stall watch reads
//! (`surfstream_runtime::watchdog`). Its event loop beats, but one final pass over a large
//! scan (re-rendering 400 tiles, writing a 2.7 GB .npy, a streamed wavelet pass) can take
//! longer than `[graph] stall_timeout_s` on its own. The algorithm crates do not depend on the
//! runtime, so they call [`beat`] here, in their long loops; the runtime installs the real
//! heartbeat with [`set_hook`]. Without a hook (tests, batch verbs) a beat does nothing.

use std::sync::OnceLock;

static HOOK: OnceLock<fn()> = OnceLock::new();

/// Installs the process's heartbeat (the first call wins).
pub fn set_hook(beat: fn()) {
    let _ = HOOK.set(beat);
}

/// Says "still working" (cheap: the hook is rate-limited; nothing without a hook).
#[inline]
pub fn beat() {
    if let Some(f) = HOOK.get() {
        f();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};

    static BEATS: AtomicUsize = AtomicUsize::new(0);

    fn count() {
        BEATS.fetch_add(1, Ordering::Relaxed);
    }

    #[test]
    fn beats_reach_the_installed_hook() {
        set_hook(count);
        let before = BEATS.load(Ordering::Relaxed);
        beat();
        beat();
        assert_eq!(BEATS.load(Ordering::Relaxed), before + 2);
    }
}
