//! Runtime dispatch of the hot loops to AVX2.
//!
//! The release build targets baseline x86-64 (SSE2), so that the binaries run on any x86-64
//! machine; there the lane loops of the NCC and plane sums spill registers and run at a third
//! of the speed. [`avx2_dispatch!`] compiles one function body twice, once with AVX2 enabled,
//! and picks the AVX2 copy when the CPU has it. The lanes are explicit in the source, so both
//! copies add in the same order and give bit-identical results (no FMA contraction either way).

/// Defines `fn NAME(ARGS) -> RET BODY`, running BODY compiled with AVX2 when the CPU supports
/// it. Helpers the body calls must be `#[inline(always)]` to be compiled with it.
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
                if !$crate::simd::baseline_forced() && std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU supports AVX2, checked just above.
                    return unsafe { avx2($($arg),*) };
                }
            }
            generic($($arg),*)
        }
    };
}

pub(crate) use avx2_dispatch;

#[cfg(test)]
thread_local! {
    static FORCE_BASELINE: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// True while [`with_baseline`] runs on this thread (tests only).
#[inline(always)]
pub(crate) fn baseline_forced() -> bool {
    #[cfg(test)]
    {
        FORCE_BASELINE.with(|f| f.get())
    }
    #[cfg(not(test))]
    {
        false
    }
}

/// Runs `f` with every dispatched function on its baseline (SSE2) copy, so tests can compare
/// the two copies.
#[cfg(test)]
pub(crate) fn with_baseline<R>(f: impl FnOnce() -> R) -> R {
    FORCE_BASELINE.with(|flag| flag.set(true));
    let r = f();
    FORCE_BASELINE.with(|flag| flag.set(false));
    r
}
