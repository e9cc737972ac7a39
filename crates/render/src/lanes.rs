//! Lanes: the instruction sets Tessera's SIMD loops are compiled for (AVX-512, AVX2, or the
//! portable `glam` lanes), chosen at run time by what the CPU has, and [`dispatch`], the one
//! trampoline that compiles a piece of code for each: the code is written once, `#[inline(always)]`
//! down to its kernels, and each instruction set gets its own copy. Every copy makes the same
//! operations in the same order (no fused multiply-add), so all give the same bits; tests run each
//! one this CPU has against the portable one.

/// Which instruction set a loop over lanes is compiled for: all three give the same bits.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lanes {
    /// Sixteen triangles in one AVX-512 register (closest hits; shadow rays take eight).
    Avx512,
    /// Eight in one AVX2 register.
    Avx2,
    /// Four in `glam`'s vectors (SSE2 on x86-64, NEON on ARM).
    Portable,
}

impl Lanes {
    /// All three, widest first.
    pub const ALL: [Lanes; 3] = [Lanes::Avx512, Lanes::Avx2, Lanes::Portable];

    /// Whether this CPU has the instructions.
    pub fn run_here(self) -> bool {
        match self {
            // The wave's loops take the byte, doubleword and vector-length extensions too;
            // every AVX-512 CPU but Xeon Phi has them (and AVX2 and the bit instructions).
            #[cfg(target_arch = "x86_64")]
            Lanes::Avx512 => {
                is_x86_feature_detected!("avx512f")
                    && is_x86_feature_detected!("avx512vl")
                    && is_x86_feature_detected!("avx512bw")
                    && is_x86_feature_detected!("avx512dq")
            }
            #[cfg(target_arch = "x86_64")]
            Lanes::Avx2 => {
                is_x86_feature_detected!("avx2")
                    && is_x86_feature_detected!("bmi1")
                    && is_x86_feature_detected!("bmi2")
                    && is_x86_feature_detected!("lzcnt")
            }
            #[cfg(not(target_arch = "x86_64"))]
            Lanes::Avx512 | Lanes::Avx2 => false,
            Lanes::Portable => true,
        }
    }

    /// The widest this CPU runs.
    pub fn widest() -> Self {
        Self::ALL.into_iter().find(|lanes| lanes.run_here()).unwrap_or(Lanes::Portable)
    }
}

impl std::fmt::Display for Lanes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Lanes::Avx512 => "16 at a time (AVX-512)",
            Lanes::Avx2 => "8 at a time (AVX2)",
            Lanes::Portable => "4 at a time (portable)",
        })
    }
}

impl Lanes {
    /// This one or `most`, whichever is narrower: for code with no use for a wider set.
    pub(crate) fn at_most(self, most: Lanes) -> Lanes {
        if self as u8 >= most as u8 { self } else { most }
    }
}

/// Runs `f` compiled for `lanes` (checked to run on this CPU): `f` and what it inlines get the
/// instruction set as a target feature, and `f` is handed `lanes` so that its kernels pick theirs.
/// The one dispatch of the crate: the wave's lane loops and the tree's walks go through it.
#[inline(always)]
pub(crate) fn dispatch<R>(lanes: Lanes, f: impl FnOnce(Lanes) -> R) -> R {
    assert!(lanes.run_here(), "{lanes} does not run on this CPU");
    // SAFETY: checked above.
    unsafe { dispatch_unchecked(lanes, f) }
}

/// [`dispatch`] without the check, for a walk of one ray, whose `lanes` were checked when its
/// tree was built (the check's feature tests cost a tree walk 0.7 % of its instructions).
///
/// # Safety
/// `lanes` must run on this CPU ([`Lanes::run_here`]).
#[inline(always)]
pub(crate) unsafe fn dispatch_unchecked<R>(lanes: Lanes, f: impl FnOnce(Lanes) -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    match lanes {
        // SAFETY: the caller's promise.
        Lanes::Avx512 => return unsafe { avx512(f) },
        // SAFETY: as above.
        Lanes::Avx2 => return unsafe { avx2(f) },
        Lanes::Portable => {}
    }
    f(Lanes::Portable)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,avx512f,avx512vl,avx512bw,avx512dq")]
fn avx512<R>(f: impl FnOnce(Lanes) -> R) -> R {
    f(Lanes::Avx512)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt")]
fn avx2<R>(f: impl FnOnce(Lanes) -> R) -> R {
    f(Lanes::Avx2)
}
