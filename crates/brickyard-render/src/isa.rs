//! Instruction sets chosen at run time. The builds target baseline x86-64
//! (SSE2), so that one binary runs on every x86-64 processor; the DVR ray
//! loop also has a copy compiled for x86-64-v3 (AVX2, FMA, BMI1/2, LZCNT,
//! MOVBE, F16C), taken where the processor has those instructions. Both
//! copies are the same source: Rust neither contracts `a·b + c` into a
//! fused multiply-add nor reorders floating-point arithmetic without being
//! told, so they give the same bits (`tests/lanes.rs` compares them). The
//! gain is in the code around the arithmetic: three-operand instructions,
//! rounding without library calls, wider moves, bit manipulation.

/// The features the x86-64-v3 copies are compiled with (`target_feature`
/// lists them again: attributes take literals only).
#[cfg(target_arch = "x86_64")]
#[inline]
fn detect() -> bool {
    std::arch::is_x86_feature_detected!("avx")
        && std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("bmi1")
        && std::arch::is_x86_feature_detected!("bmi2")
        && std::arch::is_x86_feature_detected!("f16c")
        && std::arch::is_x86_feature_detected!("fma")
        && std::arch::is_x86_feature_detected!("lzcnt")
        && std::arch::is_x86_feature_detected!("movbe")
        && std::arch::is_x86_feature_detected!("popcnt")
        && std::arch::is_x86_feature_detected!("sse3")
        && std::arch::is_x86_feature_detected!("ssse3")
        && std::arch::is_x86_feature_detected!("sse4.1")
        && std::arch::is_x86_feature_detected!("sse4.2")
}

/// Whether this processor runs the x86-64-v3 copies (always `false` on
/// other architectures). The standard library caches the detection.
pub fn x86_64_v3() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        detect()
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}
