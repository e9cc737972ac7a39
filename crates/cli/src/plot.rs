//! Charts drawn with plotters need a font; Tessera ships DejaVu Sans (Bitstream Vera licence,
//! `assets/DejaVuSans-LICENSE.txt`) so that plots look the same on every machine.

static DEJAVU_SANS: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

/// Registers the shipped font as "sans-serif" (once; later calls do nothing).
pub fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let _ = plotters::style::register_font("sans-serif", plotters::style::FontStyle::Normal, DEJAVU_SANS);
    });
}
