//! Which layer of the configuration an error comes from (the file, an `SDSEM_…` environment
//! variable, a `--set`), and what it says in words a user can act on: the key, the cause,
//! and for a near miss of a known key or value, the one meant ("did you mean …?", by edit
//! distance over the names serde expects there).

use std::fmt;
use std::path::PathBuf;

use crate::acquisition::run_dir::printable;

/// A layer of the configuration, as an error names it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Layer {
    /// The configuration file (or the recorded text, named by its origin).
    File(PathBuf),
    /// An environment variable `SDSEM_<SECTION>__<KEY>` and its value.
    Env { name: String, value: String },
    /// A `--set key=value` argument.
    Set(String),
}

impl fmt::Display for Layer {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::File(path) => write!(f, "{}", path.display()),
            Self::Env { name, value } => write!(
                f,
                "environment variable {}={:?}",
                printable(name, 80),
                printable(value, 80)
            ),
            Self::Set(arg) => write!(f, "--set {}", printable(arg, 120)),
        }
    }
}

/// The environment variable that sets `key` (`series.end_tilt_deg` → `SDSEM_SERIES__END_TILT_DEG`).
#[must_use]
pub fn env_name(key: &str) -> String {
    format!(
        "{}{}",
        super::ENV_PREFIX,
        key.to_ascii_uppercase().replace('.', "__")
    )
}

/// `error` in one line, naming the key: an unknown key or value with the one meant when it
/// is a near miss (`key` is the full key the layer sets, when it sets one).
#[must_use]
pub fn explain(error: &config::ConfigError, layer: &Layer, key: Option<&str>) -> String {
    match error {
        config::ConfigError::At {
            error: inner,
            key: at,
            ..
        } => match inner.as_ref() {
            config::ConfigError::Message(message) => {
                explain_message(message, at.as_deref(), layer, key)
            }
            other => match at {
                Some(at) => format!("{at}: {}", one_line(&other.to_string())),
                None => one_line(&other.to_string()),
            },
        },
        config::ConfigError::Message(message) => explain_message(message, None, layer, key),
        config::ConfigError::Type {
            unexpected,
            expected,
            key: at,
            ..
        } => {
            let at = at.as_deref().or(key).unwrap_or("a key");
            format!("{at}: expected {expected}, found {unexpected}")
        }
        config::ConfigError::FileParse { cause, .. } => one_line(&cause.to_string()),
        other => one_line(&other.to_string()),
    }
}

/// A serde message (`unknown field …`, `unknown variant …`) at `at`, explained.
fn explain_message(message: &str, at: Option<&str>, layer: &Layer, key: Option<&str>) -> String {
    let quoted = backquoted(message);
    let joined = |parent: Option<&str>, name: &str| match parent {
        Some(p) if !p.is_empty() => format!("{p}.{name}"),
        _ => name.to_owned(),
    };
    if let Some((given, expected)) = message
        .starts_with("unknown field")
        .then(|| quoted.split_first())
        .flatten()
    {
        let unknown = joined(at, given);
        let rendered = rendered_keys(at.unwrap_or(""));
        let expected = with_rendered(expected, &rendered);
        let expected = expected.as_slice();
        let Some(meant) = closest(given, expected) else {
            let known = if expected.is_empty() {
                "no keys".to_owned()
            } else {
                expected.join(", ")
            };
            let section = at.filter(|a| !a.is_empty()).unwrap_or("the configuration");
            return format!("unknown key {unknown} ({section} has {known})");
        };
        // The whole key the layer set, with the part that was wrong replaced.
        let mut meant = joined(at, meant);
        if let Some(rest) = key.and_then(|k| k.strip_prefix(&unknown)) {
            meant.push_str(rest);
        }
        let meant = match layer {
            Layer::Env { .. } => env_name(&meant),
            _ => meant,
        };
        return format!("unknown key {unknown}: did you mean {meant}?");
    }
    if let Some((given, expected)) = message
        .starts_with("unknown variant")
        .then(|| quoted.split_first())
        .flatten()
    {
        let at = at.or(key).unwrap_or("a key");
        let hint = closest(given, expected).map_or_else(
            || format!("expected one of {}", expected.join(", ")),
            |meant| format!("did you mean \"{meant}\"?"),
        );
        return format!("{at} = \"{given}\" is not a known value: {hint}");
    }
    // The config crate's own word for an unknown enum value; serde's names the values known.
    if let (Some(given), Some(at)) = (
        message
            .split_once("does not have variant constructor ")
            .map(|(_, g)| g.trim()),
        at.or(key),
    ) {
        let expected = known_values(at, given);
        let expected: Vec<&str> = expected.iter().map(String::as_str).collect();
        let hint = closest(given, &expected).map_or_else(
            || format!("expected one of {}", expected.join(", ")),
            |meant| format!("did you mean \"{meant}\"?"),
        );
        return format!("{at} = \"{given}\" is not a known value: {hint}");
    }
    match at.or(key) {
        Some(at) => format!("{at}: {}", one_line(message)),
        None => one_line(message),
    }
}

/// The values serde knows for the enum at dotted `key`: the defaults with `given` put there,
/// read back, name them in their refusal.
fn known_values(key: &str, given: &str) -> Vec<String> {
    let Ok(mut root) = toml::from_str::<toml::Table>(&super::Config::default().to_toml()) else {
        return Vec::new();
    };
    let mut parts: Vec<&str> = key.split('.').collect();
    let Some(last) = parts.pop() else {
        return Vec::new();
    };
    let mut table = &mut root;
    for part in parts {
        let Some(toml::Value::Table(t)) = table.get_mut(part) else {
            return Vec::new();
        };
        table = t;
    }
    table.insert(last.to_owned(), toml::Value::String(given.to_owned()));
    let Err(e) = toml::Value::Table(root).try_into::<super::Config>() else {
        return Vec::new();
    };
    let message = e.to_string();
    message
        .split_once("unknown variant")
        .map(|(_, rest)| {
            backquoted(rest)
                .into_iter()
                .skip(1)
                .map(str::to_owned)
                .collect()
        })
        .unwrap_or_default()
}

/// For a serde message about dotted `key` (`unknown field \`widht\`, expected …`, `unknown
/// variant …`), the key or value meant when the given one is a near miss.
#[must_use]
pub fn meant(message: &str, key: &str) -> Option<String> {
    let quoted = backquoted(message);
    let (given, expected) = quoted.split_first()?;
    if message.starts_with("unknown variant") {
        return Some(format!("\"{}\"", closest(given, expected)?));
    }
    if !message.starts_with("unknown field") {
        return None;
    }
    // The whole key, with the part that was wrong replaced.
    let parts: Vec<&str> = key.split('.').collect();
    let at = parts.iter().rposition(|p| p == given)?;
    let rendered = rendered_keys(&parts[..at].join("."));
    let meant = closest(given, &with_rendered(expected, &rendered))?;
    let mut whole: Vec<&str> = parts[..at].to_vec();
    whole.push(meant);
    whole.extend(&parts[at + 1..]);
    Some(whole.join("."))
}

/// The keys of the table at dotted `at` in the rendered defaults (a flattened table's
/// serde message names none).
fn rendered_keys(at: &str) -> Vec<String> {
    let Ok(mut table) = toml::from_str::<toml::Table>(&super::Config::default().to_toml()) else {
        return Vec::new();
    };
    for part in at.split('.').filter(|p| !p.is_empty()) {
        let Some(toml::Value::Table(t)) = table.remove(part) else {
            return Vec::new();
        };
        table = t;
    }
    table.keys().cloned().collect()
}

/// `expected` and the `rendered` names it lacks.
fn with_rendered<'a>(expected: &[&'a str], rendered: &'a [String]) -> Vec<&'a str> {
    let mut all = expected.to_vec();
    for r in rendered {
        if !all.contains(&r.as_str()) {
            all.push(r);
        }
    }
    all
}

/// The names between backquotes in a serde message, in order.
fn backquoted(message: &str) -> Vec<&str> {
    message.split('`').skip(1).step_by(2).collect()
}

/// The candidate `given` most likely misspells: the nearest by edit distance when the
/// distance is small for its length, or one that begins with it (a unit suffix left out).
#[must_use]
pub fn closest<'a>(given: &str, candidates: &[&'a str]) -> Option<&'a str> {
    let near = candidates
        .iter()
        .map(|c| (strsim::levenshtein(given, c), *c))
        .filter(|(d, _)| *d <= (given.chars().count() / 3).max(2))
        .min_by_key(|(d, _)| *d)
        .map(|(_, c)| c);
    near.or_else(|| {
        candidates
            .iter()
            .copied()
            .find(|c| given.chars().count() >= 3 && c.starts_with(given))
    })
}

/// A message on one line: a parser's drawing of the spot (TOML) cut down to its first and
/// last lines.
pub(super) fn one_line(text: &str) -> String {
    let lines: Vec<&str> = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect();
    match lines.as_slice() {
        [] => String::new(),
        [one] => (*one).to_owned(),
        [first, .., last] => format!("{first}: {last}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn near_misses_find_the_key_meant() {
        let keys = ["start_tilt_deg", "end_tilt_deg", "step_deg"];
        assert_eq!(closest("end_tilt", &keys), Some("end_tilt_deg"));
        assert_eq!(closest("end_tiltdeg", &keys), Some("end_tilt_deg"));
        assert_eq!(closest("stpe_deg", &keys), Some("step_deg"));
        assert_eq!(closest("colour", &keys), None);
        assert_eq!(closest("papr", &["paper", "improved"]), Some("paper"));
    }

    #[test]
    fn a_parser_drawing_becomes_one_line() {
        let text = "TOML parse error at line 2, column 5\n  |\n2 | a = \n  |     ^\nstring values must be quoted\n";
        assert_eq!(
            one_line(text),
            "TOML parse error at line 2, column 5: string values must be quoted"
        );
    }
}
