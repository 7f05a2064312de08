//! Axis identifiers.

use std::fmt;

use serde::{Deserialize, Serialize};

/// Longest axis identifier accepted (PI controllers allow up to 8 characters).
pub const MAX_AXIS_ID_LEN: usize = 8;

/// A GCS axis identifier such as `1`, `X` or `T`: 1 to 8 ASCII letters, digits or `_`.
///
/// Identifiers are case-sensitive, as on the controllers.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct AxisId(String);

/// Why a string is not an axis identifier.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error(
    "invalid GCS axis identifier {id:?}: use 1 to {MAX_AXIS_ID_LEN} ASCII letters, digits or '_'"
)]
pub struct AxisIdError {
    /// The rejected text.
    pub id: String,
}

impl AxisId {
    /// Checks and wraps an axis identifier.
    pub fn new(id: impl Into<String>) -> Result<Self, AxisIdError> {
        let id = id.into();
        let valid = !id.is_empty()
            && id.len() <= MAX_AXIS_ID_LEN
            && id.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_');
        if valid {
            Ok(Self(id))
        } else {
            Err(AxisIdError { id })
        }
    }

    /// The identifier as sent on the wire.
    pub fn as_str(&self) -> &str {
        &self.0
    }

    /// Parses a list such as `["X", "Y", "T"]`.
    pub fn list<S: AsRef<str>>(ids: &[S]) -> Result<Vec<Self>, AxisIdError> {
        ids.iter().map(|s| Self::new(s.as_ref())).collect()
    }
}

impl TryFrom<String> for AxisId {
    type Error = AxisIdError;
    fn try_from(value: String) -> Result<Self, Self::Error> {
        Self::new(value)
    }
}

impl TryFrom<&str> for AxisId {
    type Error = AxisIdError;
    fn try_from(value: &str) -> Result<Self, Self::Error> {
        Self::new(value)
    }
}

impl From<AxisId> for String {
    fn from(value: AxisId) -> Self {
        value.0
    }
}

impl fmt::Display for AxisId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accepts_controller_style_names() {
        for ok in ["1", "X", "T", "AXIS_1", "12345678"] {
            assert_eq!(AxisId::new(ok).unwrap().as_str(), ok);
        }
    }

    #[test]
    fn rejects_names_that_would_break_the_line_syntax() {
        for bad in ["", "X Y", "X=1", "123456789", "É", "X\n"] {
            assert!(AxisId::new(bad).is_err(), "{bad:?} accepted");
        }
    }

    #[test]
    fn deserialises_through_validation() {
        let ok: AxisId = serde_json::from_str("\"T\"").unwrap();
        assert_eq!(ok.as_str(), "T");
        assert!(serde_json::from_str::<AxisId>("\"a b\"").is_err());
    }
}
