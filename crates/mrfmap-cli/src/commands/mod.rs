//! One module per subcommand; the small map operations (crop, clear, merge, diff, project)
//! share `ops`, and the flag groups several commands take live in `options`.

#[cfg(feature = "bags")]
pub mod bag;
pub mod bench;
pub mod build;
pub mod calibrate;
pub mod compare;
pub mod demo;
pub mod eval;
pub mod experiment;
pub mod export;
pub mod info;
pub mod loo;
pub mod noise;
pub mod ops;
pub mod options;
pub mod protocol;
pub mod query;
pub mod scaling;
pub mod simulate;
pub mod view;
pub mod views;

use clap::builder::TypedValueParser;
use mrfmap::Choice;

/// clap parser for a strictly positive, finite number (resolution, max range).
pub fn positive(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v > 0.0 && v.is_finite() => Ok(v),
        Ok(v) => Err(format!("must be a positive number, got {v}")),
        Err(e) => Err(e.to_string()),
    }
}

/// clap parser for an option with a fixed set of names ([`Choice`]): its names are the
/// possible values (listed in `--help` and in errors, completed by shells).
pub fn choice<T: Choice + Send + Sync>() -> impl clap::builder::TypedValueParser<Value = T> {
    clap::builder::PossibleValuesParser::new(T::ALL.iter().map(|v| v.name())).try_map(|s| T::parse(&s))
}

/// clap parser for a positive number or `inf`.
pub fn positive_or_infinite(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v > 0.0 && !v.is_nan() => Ok(v),
        Ok(v) => Err(format!("must be a positive number or inf, got {v}")),
        Err(e) => Err(e.to_string()),
    }
}

/// clap parser for an occupancy threshold: a probability in `[0, 1)` (nothing is above 1, so a
/// larger threshold would select nothing and give an empty output).
pub fn threshold(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if (0.0..1.0).contains(&v) => Ok(v),
        Ok(v) => Err(format!("must be an occupancy in [0, 1), got {v}")),
        Err(e) => Err(e.to_string()),
    }
}

/// clap parser for a finite number that is 0 or more.
pub fn non_negative(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v >= 0.0 && v.is_finite() => Ok(v),
        Ok(v) => Err(format!("must be 0 or a positive number, got {v}")),
        Err(e) => Err(e.to_string()),
    }
}
