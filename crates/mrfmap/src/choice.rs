//! Options that take one of a few names (an engine, an allocation, a marking, ...): one
//! list of values and names per option, which the command line offers as its possible
//! values, Python and files parse, and errors list. Each option's type implements
//! [`Choice`] beside its definition.

use crate::error::{Error, Result};

/// A value of an option with a fixed set of names.
///
/// ```
/// use mrfmap::Choice;
/// use mrfmap::inference::{Allocation, EngineKind};
/// assert_eq!(EngineKind::parse("crm").unwrap(), EngineKind::Crm);
/// assert_eq!(Allocation::Full.name(), "full");
/// let e = EngineKind::parse("octo").unwrap_err().to_string();
/// assert!(e.contains("unknown engine \"octo\"") && e.contains("logodds, mrf, crm"), "{e}");
/// ```
pub trait Choice: Copy + Sized + 'static {
    /// What the option is called in messages ("engine").
    const WHAT: &'static str;
    /// Every value, in the order they are listed.
    const ALL: &'static [Self];

    /// The value's name on the command line, in Python and in files.
    fn name(self) -> &'static str;

    /// The value named `s`; an error naming the option and listing the names otherwise.
    fn parse(s: &str) -> Result<Self> {
        Self::ALL.iter().copied().find(|v| v.name() == s).ok_or_else(|| {
            let names: Vec<_> = Self::ALL.iter().map(|v| v.name()).collect();
            Error::Invalid(format!("unknown {} {s:?}; available: {}", Self::WHAT, names.join(", ")))
        })
    }
}

/// Implements [`Choice`] for a fieldless enum: `choice!(Type, "what", Variant => "name", ...)`,
/// the variants in the order they are listed.
macro_rules! choice {
    ($ty:ident, $what:literal, $($variant:ident => $name:literal),+ $(,)?) => {
        impl $crate::Choice for $ty {
            const WHAT: &'static str = $what;
            const ALL: &'static [Self] = &[$($ty::$variant),+];

            fn name(self) -> &'static str {
                match self {
                    $($ty::$variant => $name),+
                }
            }
        }
    };
}
pub(crate) use choice;
