//! Numbers as a person reads them: the one place that decides how many digits a value shows.
//!
//! * [`sig`]: any value with `n` significant figures, in fixed-point where that reads well
//!   ("2.280", "0.001000", "1235"), scientific otherwise ("1.23e-7").
//! * [`height`] / [`height_unicode`]: a height (or any length in µm a person compares by
//!   size) with 3 significant figures and a unit that suits it, nm below 1 µm: "5.12 nm",
//!   "1.27 um", "15.3 um". A 3 x 3 MetroPro map (Sa 5.1 nm) read "Sa 0.005 um" at three
//!   decimals, Sdr "0.00 %": fixed decimals drop the digits that matter on smooth surfaces.
//!
//! The verdict, report.html, the verbs' console lines and Python's repr all print through
//! these; the JSON records keep the numbers as they are.

/// Significant figures of a height: 3 (the ISO 25178 parameters' usual precision; a
/// measurement's repeatability is rarely better than 1 %).
pub const HEIGHT_DIGITS: usize = 3;

/// `v` with `digits` (at least 1) significant figures, trailing zeros kept (they are
/// significant): fixed-point for 1e-5 <= |v| < 1e7, scientific (`1.23e-7`) beyond; "0" for
/// zero; "NaN", "inf", "-inf" as Rust writes them.
pub fn sig(v: f64, digits: usize) -> String {
    if !v.is_finite() {
        return format!("{v}");
    }
    if v == 0.0 {
        return "0".into();
    }
    let digits = digits.max(1);
    // The exponent after rounding to `digits` figures (9.996 to 3 figures is 10.0, not 9.996),
    // read from Rust's own correctly rounded scientific form.
    let e = decimal_exponent(v, digits);
    if (-5..7).contains(&e) {
        let decimals = (digits as i32 - 1 - e).max(0) as usize;
        format!("{v:.decimals$}")
    } else {
        format!("{v:.*e}", digits - 1)
    }
}

/// The power of ten of `v`'s leading digit once rounded to `digits` figures.
fn decimal_exponent(v: f64, digits: usize) -> i32 {
    let s = format!("{v:.*e}", digits - 1);
    s.rsplit_once('e')
        .and_then(|(_, e)| e.parse().ok())
        .unwrap_or_else(|| v.abs().log10().floor() as i32)
}

/// A height in µm as terminals print it: [`HEIGHT_DIGITS`] significant figures, in nm below
/// 1 µm ("5.12 nm", "1.27 um", "15.3 um", "1585 um"); "NaN" etc. for a non-finite value.
pub fn height(v_um: f64) -> String {
    height_in(v_um, "um")
}

/// [`height`] with the micro sign, for pages (report.html, finish.html): "1.27 µm".
pub fn height_unicode(v_um: f64) -> String {
    height_in(v_um, "µm")
}

fn height_in(v_um: f64, micrometre: &str) -> String {
    if !v_um.is_finite() {
        return format!("{v_um}");
    }
    if v_um == 0.0 {
        return format!("0 {micrometre}");
    }
    // The unit by the rounded value: 0.9996 um is "1.00 um", not "1000 nm".
    if decimal_exponent(v_um, HEIGHT_DIGITS) < 0 {
        format!("{} nm", sig(v_um * 1000.0, HEIGHT_DIGITS))
    } else {
        format!("{} {micrometre}", sig(v_um, HEIGHT_DIGITS))
    }
}

/// A percentage with [`HEIGHT_DIGITS`] significant figures: "0.00123 %", "12.3 %".
pub fn percent(v_pct: f64) -> String {
    format!("{} %", sig(v_pct, HEIGHT_DIGITS))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heights_read_with_three_figures_and_nm_below_one_micrometre() {
        assert_eq!(height(0.00512), "5.12 nm");
        assert_eq!(height(1.2712), "1.27 um");
        assert_eq!(height(15.27), "15.3 um");
        assert_eq!(height(-0.0734), "-73.4 nm");
        assert_eq!(height(1584.8), "1585 um");
        assert_eq!(height(0.0000004), "0.000400 nm");
        assert_eq!(height(1.2), "1.20 um");
        assert_eq!(height(0.0), "0 um");
        assert_eq!(height(f64::NAN), "NaN");
        assert_eq!(height_unicode(0.5), "500 nm");
        assert_eq!(height_unicode(2.0), "2.00 µm");
        // The unit follows the rounded value.
        assert_eq!(height(0.9996), "1.00 um");
        assert_eq!(height(0.99949), "999 nm");
    }

    #[test]
    fn significant_figures_round_once_and_switch_to_scientific_far_out() {
        assert_eq!(sig(2.28, 4), "2.280");
        assert_eq!(sig(0.001, 4), "0.001000");
        assert_eq!(sig(1234.5678, 4), "1235");
        assert_eq!(sig(9.996, 3), "10.0");
        assert_eq!(sig(0.0, 4), "0");
        assert_eq!(sig(-0.00001234, 3), "-0.0000123");
        assert_eq!(sig(1.234e-7, 3), "1.23e-7");
        assert_eq!(sig(12_345_678.0, 3), "1.23e7");
        assert_eq!(sig(f64::INFINITY, 3), "inf");
        assert_eq!(sig(5.0, 0), "5");
        assert_eq!(percent(0.0012345), "0.00123 %");
        assert_eq!(percent(12.34), "12.3 %");
    }
}
