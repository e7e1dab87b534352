//! Eight float lanes in either precision, so that one kernel (the specular lobe, the PBR
//! block gather, the linearised shading) serves both: f64x8 for the gradient checks and the
//! reference paths, f32x8 where the training iteration spends its time.
//!
//! Why both: on AVX2 an f64x8 operation is two instructions and f64 divisions and square roots
//! are slower still, while the kernel's inputs are f32 anyway; f32 lanes halve the arithmetic.
//! The finite-difference tests cannot run on f32 arithmetic (a step of 1e-4 over rounding of
//! 1e-7 leaves 1e-3 of noise), so they check the f64 instantiation and a separate test bounds
//! the f32 one's distance from it.

use super::brdf_lanes::LANES;
use std::ops::{Add, AddAssign, BitOr, Div, Mul, Neg, Sub};
use wide::{f32x8, f64x8};

/// Eight lanes of f32 or f64. Comparisons return masks of the same type (all bits set where
/// true), as `wide` does.
pub trait FloatLanes:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + BitOr<Output = Self>
    + AddAssign
{
    const ZERO: Self;
    fn splat(x: f64) -> Self;
    fn from_f32s(x: [f32; LANES]) -> Self;
    fn from_f64s(x: [f64; LANES]) -> Self;
    fn to_f64s(self) -> [f64; LANES];
    fn to_f32s(self) -> [f32; LANES];
    fn sqrt(self) -> Self;
    fn gt(self, rhs: Self) -> Self;
    fn lt(self, rhs: Self) -> Self;
    /// `self` a mask: `if_true` where set, else `if_false`.
    fn select(self, if_true: Self, if_false: Self) -> Self;
    fn bitmask(self) -> u32;
    fn max(self, rhs: Self) -> Self;
    /// The lanes summed in lane order, in f64 (a fixed order: the result does not depend on the
    /// SIMD width).
    #[inline]
    fn sum(self) -> f64 {
        self.to_f64s().iter().sum()
    }
}

/// The impl for `$lanes` of `$elem`: the same code for both, conversions by `as`.
macro_rules! float_lanes {
    ($lanes:ident, $elem:ty) => {
        impl FloatLanes for $lanes {
            const ZERO: Self = $lanes::ZERO;
            #[inline]
            fn splat(x: f64) -> Self {
                $lanes::splat(x as $elem)
            }
            #[inline]
            fn from_f32s(x: [f32; LANES]) -> Self {
                $lanes::from(x.map(|v| v as $elem))
            }
            #[inline]
            fn from_f64s(x: [f64; LANES]) -> Self {
                $lanes::from(x.map(|v| v as $elem))
            }
            #[inline]
            fn to_f64s(self) -> [f64; LANES] {
                self.to_array().map(|v| v as f64)
            }
            #[inline]
            fn to_f32s(self) -> [f32; LANES] {
                self.to_array().map(|v| v as f32)
            }
            #[inline]
            fn sqrt(self) -> Self {
                $lanes::sqrt(self)
            }
            #[inline]
            fn gt(self, rhs: Self) -> Self {
                self.simd_gt(rhs)
            }
            #[inline]
            fn lt(self, rhs: Self) -> Self {
                self.simd_lt(rhs)
            }
            #[inline]
            fn select(self, if_true: Self, if_false: Self) -> Self {
                $lanes::select(self, if_true, if_false)
            }
            #[inline]
            fn bitmask(self) -> u32 {
                self.to_bitmask()
            }
            #[inline]
            fn max(self, rhs: Self) -> Self {
                $lanes::max(self, rhs)
            }
        }
    };
}

float_lanes!(f64x8, f64);
float_lanes!(f32x8, f32);

#[cfg(test)]
mod tests {
    use super::*;

    /// Both instantiations agree on the operations the kernels use (masks, select, order of
    /// the lane sum).
    fn check<L: FloatLanes>() {
        let a = L::from_f64s([1.0, -2.0, 3.0, 0.5, 0.0, -0.25, 8.0, 4.0]);
        let b = L::splat(0.75);
        let m = a.gt(b);
        assert_eq!(m.bitmask(), 0b1100_0101);
        assert_eq!(a.lt(b).bitmask(), 0b0011_1010);
        assert_eq!(m.select(a, b).to_f64s(), [1.0, 0.75, 3.0, 0.75, 0.75, 0.75, 8.0, 4.0]);
        assert_eq!((m | a.lt(b)).bitmask(), 0xff);
        assert_eq!(a.max(b).to_f64s()[1], 0.75);
        assert_eq!((a * a).sqrt().to_f64s()[1], 2.0);
        assert_eq!(a.sum(), 14.25);
        assert_eq!((-a).to_f32s()[0], -1.0);
        assert_eq!(L::from_f32s([2.0; LANES]).to_f64s(), [2.0; LANES]);
        assert_eq!(L::ZERO.to_f64s(), [0.0; LANES]);
    }

    #[test]
    fn both_precisions_behave_alike() {
        check::<f64x8>();
        check::<f32x8>();
    }
}
