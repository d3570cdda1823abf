//! Flag bit values of the ICD, in one place. The model takes them as arguments
//! ([`crate::model::FlagBits`]); products and tests name them from here.

/// Bit numbers of the on-board flag plane `/flags` (ICD table "On-board flag bits").
pub mod bits {
    pub const TRANSIENT: u32 = 1 << 0;
    pub const OVERFLOW: u32 = 1 << 1;
    pub const SUR_ERROR: u32 = 1 << 2;
    pub const NONFUNC: u32 = 1 << 6;
    /// Set by this stage in its output, never by upstream.
    pub const PERSIST: u32 = 1 << 17;
}

/// Bits of `/persistence/flags` (uint8), ICD "Output".
pub mod pbits {
    /// Predicted current above the high threshold (and not released).
    pub const HIGH: u8 = 1 << 0;
    /// Predicted current above the low threshold.
    pub const LOW: u8 = 1 << 1;
    /// The previous exposure's fluence was unknown (TRANSIENT, or no usable slope):
    /// the maximum amplitude of the knot table was used, and the pixel is flagged.
    pub const MAX_AMPLITUDE: u8 = 1 << 2;
    /// Released early in this exposure (measured current low three times running).
    pub const RELEASED: u8 = 1 << 3;
    /// An earlier exposure of this detector is missing or was rejected.
    pub const HISTORY_INCOMPLETE: u8 = 1 << 4;
}
