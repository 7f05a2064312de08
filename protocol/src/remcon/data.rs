//! The data of `>` status lines: parsing (client) and formatting (server).

/// Why the data of a status line is not the answer to the query sent.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("expected {what}, got {data:?}")]
pub struct DataError {
    /// What the query answers.
    pub what: &'static str,
    /// The data received.
    pub data: String,
}

fn bad(what: &'static str, data: &str) -> DataError {
    DataError {
        what,
        data: data.to_owned(),
    }
}

fn finite(word: &str) -> Option<f64> {
    word.parse::<f64>().ok().filter(|v| v.is_finite())
}

/// The answer to `C95?`: `x y z t r m moving` (mm, mm, mm, °, °, mm, flag).
/// Axes the stage lacks read `0.0` [OD-Z].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StageReading {
    /// X, mm.
    pub x_mm: f64,
    /// Y, mm.
    pub y_mm: f64,
    /// Z, mm.
    pub z_mm: f64,
    /// Tilt, degrees.
    pub t_deg: f64,
    /// Rotation, degrees.
    pub r_deg: f64,
    /// M, mm.
    pub m_mm: f64,
    /// The moving flag: `1.0` moving, `0.0` idle.
    pub moving: bool,
}

impl StageReading {
    const WHAT: &'static str = "seven numbers `x y z t r m moving` with moving 0 or 1";

    /// Parses the data of the `C95?` status line.
    pub fn parse(data: &str) -> Result<Self, DataError> {
        let words: Vec<&str> = data.split_ascii_whitespace().collect();
        let [x, y, z, t, r, m, moving] = words.as_slice() else {
            return Err(bad(Self::WHAT, data));
        };
        let v: Option<Vec<f64>> = [x, y, z, t, r, m].iter().map(|w| finite(w)).collect();
        let v = v.ok_or_else(|| bad(Self::WHAT, data))?;
        // The flag is compared as a number: `1.0`, `1` and `1.000000` all mean moving.
        let moving = match finite(moving) {
            Some(1.0) => true,
            Some(0.0) => false,
            _ => return Err(bad(Self::WHAT, data)),
        };
        Ok(Self {
            x_mm: v[0],
            y_mm: v[1],
            z_mm: v[2],
            t_deg: v[3],
            r_deg: v[4],
            m_mm: v[5],
            moving,
        })
    }

    /// The data of the status line (server side): six decimals, flag `1.0`/`0.0`.
    pub fn to_data(&self) -> String {
        let n = |v: f64| format!("{:.6}", if v == 0.0 { 0.0 } else { v });
        format!(
            "{} {} {} {} {} {} {}",
            n(self.x_mm),
            n(self.y_mm),
            n(self.z_mm),
            n(self.t_deg),
            n(self.r_deg),
            n(self.m_mm),
            if self.moving { "1.0" } else { "0.0" }
        )
    }
}

/// The answer to `IST?`: `type init`, init 0 = initialised, 1 = not [SF].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StageInit {
    /// The stage type number.
    pub stage_type: i64,
    /// Whether the stage is initialised.
    pub initialised: bool,
}

impl StageInit {
    /// Parses the data of the `IST?` status line.
    pub fn parse(data: &str) -> Result<Self, DataError> {
        const WHAT: &str = "two integers `type init` with init 0 or 1";
        let words: Vec<&str> = data.split_ascii_whitespace().collect();
        let [stage_type, init] = words.as_slice() else {
            return Err(bad(WHAT, data));
        };
        let stage_type = stage_type.parse::<i64>().map_err(|_| bad(WHAT, data))?;
        let initialised = match *init {
            "0" => true,
            "1" => false,
            _ => return Err(bad(WHAT, data)),
        };
        Ok(Self {
            stage_type,
            initialised,
        })
    }

    /// The data of the status line (server side).
    pub fn to_data(&self) -> String {
        format!("{} {}", self.stage_type, u8::from(!self.initialised))
    }
}

/// One number (`PIX?` nm, `MAG?`).
pub fn parse_number(data: &str) -> Result<f64, DataError> {
    finite(data.trim()).ok_or_else(|| bad("a number", data))
}

/// One count (`PHN?`).
pub fn parse_count(data: &str) -> Result<u64, DataError> {
    data.trim()
        .parse::<u64>()
        .map_err(|_| bad("a non-negative integer", data))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn c95_reading_in_every_documented_form() {
        let r = StageReading::parse("12.5 40.000000 10 3.0 180 0.0 1.0").unwrap();
        assert_eq!(
            r,
            StageReading {
                x_mm: 12.5,
                y_mm: 40.0,
                z_mm: 10.0,
                t_deg: 3.0,
                r_deg: 180.0,
                m_mm: 0.0,
                moving: true
            }
        );
        assert!(!StageReading::parse("0 0 0 0 0 0 0.0").unwrap().moving);
        assert!(StageReading::parse("0 0 0 0 0 0 1").unwrap().moving);
        for bad in [
            "",
            "0 0 0 0 0 0",
            "0 0 0 0 0 0 0 0",
            "0 0 x 0 0 0 0",
            "0 0 0 0 0 0 0.5",
            "0 0 0 nan 0 0 0",
        ] {
            assert!(StageReading::parse(bad).is_err(), "{bad:?}");
        }
        assert_eq!(
            StageReading::parse(&r.to_data()).unwrap(),
            r,
            "server form parses back"
        );
        assert_eq!(
            r.to_data(),
            "12.500000 40.000000 10.000000 3.000000 180.000000 0.000000 1.0"
        );
    }

    #[test]
    fn ist_and_single_values() {
        assert_eq!(
            StageInit::parse("2 0").unwrap(),
            StageInit {
                stage_type: 2,
                initialised: true
            }
        );
        assert!(!StageInit::parse("2 1").unwrap().initialised);
        assert!(StageInit::parse("2").is_err());
        assert!(StageInit::parse("2 x").is_err());
        let s = StageInit {
            stage_type: 5,
            initialised: false,
        };
        assert_eq!(StageInit::parse(&s.to_data()).unwrap(), s);
        assert_eq!(parse_number(" 593.3 ").unwrap(), 593.3);
        assert!(parse_number("").is_err());
        assert_eq!(parse_count("17").unwrap(), 17);
        assert!(parse_count("-1").is_err());
    }
}
