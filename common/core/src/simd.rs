//! Runtime dispatch of hot loops to AVX2: the one scheme every crate uses.
//!
//! The release build targets baseline x86-64 (SSE2), so that the binaries run on any x86-64
//! machine; there explicit-lane loops spill registers and run at a third of the speed.
//! [`avx2_dispatch!`](crate::avx2_dispatch) compiles one function body twice, once with AVX2
//! enabled, and picks the AVX2 copy when the CPU has it. With the lanes explicit in the source
//! both copies add in the same order and give bit-identical results (no FMA contraction either
//! way), which [`with_baseline`] lets a test check.

use std::sync::atomic::{AtomicUsize, Ordering};

/// Defines `fn NAME(ARGS) -> RET BODY`, running BODY compiled with AVX2 when the CPU supports
/// it. Helpers the body calls must be `#[inline(always)]` to be compiled with it.
#[macro_export]
macro_rules! avx2_dispatch {
    (
        $(#[$meta:meta])*
        $vis:vis fn $name:ident($($arg:ident : $ty:ty),* $(,)?) -> $ret:ty $body:block
    ) => {
        $(#[$meta])*
        $vis fn $name($($arg: $ty),*) -> $ret {
            #[inline(always)]
            fn generic($($arg: $ty),*) -> $ret $body
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2")]
                fn avx2($($arg: $ty),*) -> $ret {
                    generic($($arg),*)
                }
                if $crate::simd::avx2_allowed() {
                    // SAFETY: avx2_allowed() checked that the CPU supports AVX2.
                    return unsafe { avx2($($arg),*) };
                }
            }
            generic($($arg),*)
        }
    };
}

/// Number of [`with_baseline`] calls running (on any thread).
static FORCE_BASELINE: AtomicUsize = AtomicUsize::new(0);

/// True when the CPU has AVX2 and no [`with_baseline`] is running.
#[inline]
pub fn avx2_allowed() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        FORCE_BASELINE.load(Ordering::Relaxed) == 0 && std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Runs `f` with every dispatched function on its baseline (SSE2) copy, so a test can compare
/// the two copies. Process-wide while it runs: other threads may take the baseline copy too,
/// which is safe because both copies give the same bits.
pub fn with_baseline<R>(f: impl FnOnce() -> R) -> R {
    struct Release;
    impl Drop for Release {
        fn drop(&mut self) {
            FORCE_BASELINE.fetch_sub(1, Ordering::SeqCst);
        }
    }
    FORCE_BASELINE.fetch_add(1, Ordering::SeqCst);
    let _release = Release;
    f()
}

#[cfg(test)]
mod tests {
    crate::avx2_dispatch! {
        fn dot(a: &[f32], b: &[f32]) -> f32 {
            a.iter().zip(b).map(|(x, y)| x * y).sum()
        }
    }

    #[test]
    fn both_copies_agree() {
        let a: Vec<f32> = (0..1000).map(|i| (i as f32 * 0.37).sin()).collect();
        let b: Vec<f32> = (0..1000).map(|i| (i as f32 * 0.11).cos()).collect();
        let fast = dot(&a, &b);
        let base = super::with_baseline(|| dot(&a, &b));
        assert_eq!(fast.to_bits(), base.to_bits());
    }
}
