//! The instruction set this build was compiled for, checked before anything else runs: a binary
//! built for x86-64-v2 (`.cargo/config.toml`) would otherwise die of an illegal instruction, with
//! no word of why, on an older CPU.

/// A message naming what the CPU lacks, or `None` when it runs this build.
pub fn missing_features() -> Option<String> {
    #[cfg(all(target_arch = "x86_64", target_feature = "popcnt"))]
    {
        use std::arch::x86_64::__cpuid;
        // CPUID leaf 1, ECX: the x86-64-v2 features (`is_x86_feature_detected!` cannot tell:
        // it answers true at compile time for features the build enables).
        #[allow(unused_unsafe)] // `__cpuid` is an unsafe fn on older toolchains
        let ecx = unsafe { __cpuid(1) }.ecx;
        #[allow(unused_unsafe)]
        let ext_ecx = unsafe { __cpuid(0x8000_0001) }.ecx;
        let features = [
            ("SSE3", ecx, 0),
            ("SSSE3", ecx, 9),
            ("CMPXCHG16B", ecx, 13),
            ("SSE4.1", ecx, 19),
            ("SSE4.2", ecx, 20),
            ("POPCNT", ecx, 23),
            ("LAHF/SAHF", ext_ecx, 0),
        ];
        let missing: Vec<&str> =
            features.iter().filter(|(_, reg, bit)| reg & (1 << bit) == 0).map(|(name, _, _)| *name).collect();
        if !missing.is_empty() {
            return Some(format!(
                "this tessera binary was built for x86-64-v2 CPUs and this CPU lacks {}; rebuild it for \
                 this one with RUSTFLAGS=\"-C target-cpu=x86-64\" cargo build --release (the images \
                 are bit-identical)",
                missing.join(", ")
            ));
        }
    }
    None
}

#[cfg(test)]
mod tests {
    /// The machine that builds and tests this binary also runs it.
    #[test]
    fn this_cpu_runs_this_build() {
        assert_eq!(super::missing_features(), None);
    }
}
