//! Dates as the instruments write them, read into ISO 8601 for the X3P writer's `Record2`
//! (issue 35).
//!
//! Read ([`read_date`]): ISO 8601 / RFC 3339 ("2023-03-10T16:35:59", a space for the T,
//! fractions, a zone "Z", "+01:00", "+0100" or "+01"), a bare date, C's asctime
//! ("Fri Mar 10 16:35:59 2023", Sensofar .plu), "10 Mar 2023 16:35:59", "March 10, 2023",
//! "2023/03/10 16:35:59", the dotted day-first "10.03.2023 16:35", and numeric dates with
//! the year last ("10/03/2023 16:35", "3/10/2023 4:35:59 PM"). A numeric date whose day and
//! month cannot be told apart (both <= 12) is read day first (dd/mm/yyyy, the European
//! instruments' order), or month first when the time has AM / PM (the US order), and the
//! result says which was assumed.

/// A date read from an instrument's text.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReadDate {
    /// "YYYY-MM-DDTHH:MM:SS[.fff][zone]".
    pub iso: String,
    /// Set when the reading had to assume something (the order of day and month).
    pub assumed: Option<String>,
}

/// `text` as an ISO 8601 date-time, or None when it is not one of the forms of the module
/// doc. See [`read_date`] for what was assumed.
pub fn iso8601_date(text: &str) -> Option<String> {
    read_date(text).map(|d| d.iso)
}

/// `text` (trailing NULs and blanks ignored) read as a date: see the module doc.
pub fn read_date(text: &str) -> Option<ReadDate> {
    let t = text.trim().trim_end_matches('\0').trim();
    if let Some(iso) = iso8601_as_is(t) {
        return Some(ReadDate { iso, assumed: None });
    }
    instrument_date(t)
}

/// The ISO 8601 text of a zone word ("Z", "UTC", "GMT", "+01:00", "+0100", "+01"), if it is one.
fn zone_of(w: &str) -> Option<String> {
    let u = w.to_ascii_uppercase();
    if matches!(u.as_str(), "Z" | "UTC" | "GMT") {
        return Some("Z".into());
    }
    let b = u.as_bytes();
    let sign = *b.first()?;
    if !matches!(sign, b'+' | b'-') {
        return None;
    }
    let digits: String = u[1..].chars().filter(|c| *c != ':').collect();
    if !digits.bytes().all(|c| c.is_ascii_digit()) {
        return None;
    }
    let colon_ok = match u.len() {
        6 => b[3] == b':',
        3 | 5 => !u.contains(':'),
        _ => false,
    };
    let (h, m): (u32, u32) = match digits.len() {
        2 => (digits.parse().ok()?, 0),
        4 => (digits[..2].parse().ok()?, digits[2..].parse().ok()?),
        _ => return None,
    };
    (colon_ok && h <= 14 && m < 60).then(|| format!("{}{h:02}:{m:02}", sign as char))
}

/// The instruments' forms (all but ISO 8601), as "YYYY-MM-DDTHH:MM:SS[zone]".
fn instrument_date(t: &str) -> Option<ReadDate> {
    const MONTHS: [&str; 12] = [
        "jan", "feb", "mar", "apr", "may", "jun", "jul", "aug", "sep", "oct", "nov", "dec",
    ];
    let month_of = |w: &str| {
        let w = w.trim_end_matches([',', '.']).to_ascii_lowercase();
        (w.len() >= 3 && w.bytes().all(|c| c.is_ascii_alphabetic()))
            .then(|| MONTHS.iter().position(|m| w.starts_with(m)))
            .flatten()
            .map(|k| k as u32 + 1)
    };
    let is_time = |w: &str| w.contains(':') && w.split(':').all(|p| p.parse::<u32>().is_ok());
    let mut words: Vec<&str> = t.split_whitespace().collect();
    // AM / PM, and a zone word, are taken out first.
    let meridiem = words
        .iter()
        .position(|w| w.eq_ignore_ascii_case("am") || w.eq_ignore_ascii_case("pm"))
        .map(|k| words.remove(k).eq_ignore_ascii_case("pm"));
    let zone = match words
        .iter()
        .position(|w| !is_time(w) && zone_of(w).is_some())
    {
        Some(k) => zone_of(words.remove(k))?,
        None => String::new(),
    };
    let time_word = words.iter().position(|w| is_time(w));
    let time = match time_word {
        None if meridiem.is_some() => return None,
        None => "00:00:00".to_string(),
        Some(k) => {
            let p: Vec<u32> = words[k]
                .split(':')
                .map(|p| p.parse().ok())
                .collect::<Option<_>>()?;
            let (mut h, m, s) = match p[..] {
                [h, m] => (h, m, 0),
                [h, m, s] => (h, m, s),
                _ => return None,
            };
            if let Some(pm) = meridiem {
                if !(1..=12).contains(&h) {
                    return None;
                }
                h = match (pm, h) {
                    (false, 12) => 0,
                    (true, 12) => 12,
                    (true, h) => h + 12,
                    (false, h) => h,
                };
            }
            if !(h < 24 && m < 60 && s < 61) {
                return None;
            }
            format!("{h:02}:{m:02}:{s:02}")
        }
    };
    if let Some(k) = time_word {
        words.remove(k);
    }
    let rest = words;
    let mut assumed = None;
    let (year, month, day): (u32, u32, u32) =
        if let Some(k) = rest.iter().position(|w| month_of(w).is_some()) {
            // asctime "Fri Mar 10 ... 2023" or "10 Mar 2023": the numbers are the day and the year.
            let nums: Vec<u32> = rest
                .iter()
                .enumerate()
                .filter(|&(i, _)| i != k)
                .filter_map(|(_, w)| w.trim_end_matches([',', '.']).parse().ok())
                .collect();
            let (day, year) = match nums[..] {
                [a, b] if b >= 1000 => (a, b),
                [a, b] if a >= 1000 => (b, a),
                _ => return None,
            };
            (year, month_of(rest[k])?, day)
        } else if let [d] = rest[..] {
            let parts: Vec<&str> = d.split(['.', '/', '-']).collect();
            let separators: Vec<char> = d.chars().filter(|c| ".-/".contains(*c)).collect();
            if parts.len() != 3 || separators.iter().any(|c| *c != separators[0]) {
                return None;
            }
            let n: Vec<u32> = parts
                .iter()
                .map(|p| {
                    (!p.is_empty() && p.len() <= 4 && p.bytes().all(|c| c.is_ascii_digit()))
                        .then(|| p.parse().ok())
                        .flatten()
                })
                .collect::<Option<_>>()?;
            match (parts[0].len(), parts[2].len(), separators[0]) {
                // Year first: "2023/03/10".
                (4, 1..=2, '/' | '.') => (n[0], n[1], n[2]),
                // Year last. Dotted is day first by convention ("10.03.2023").
                (1..=2, 4, '.') => (n[2], n[1], n[0]),
                (1..=2, 4, _) => {
                    let (a, b) = (n[0], n[1]);
                    if a > 12 && b <= 12 {
                        (n[2], b, a)
                    } else if (b > 12 && a <= 12) || a == b {
                        // Month first, or no matter which.
                        (n[2], a, b)
                    } else if meridiem.is_some() {
                        assumed = Some(format!(
                            "{d:?} read month first (mm/dd/yyyy: the time has AM/PM, the US order)"
                        ));
                        (n[2], a, b)
                    } else {
                        assumed = Some(format!(
                            "{d:?} read day first (dd/mm/yyyy): day and month cannot be told apart"
                        ));
                        (n[2], b, a)
                    }
                }
                _ => return None,
            }
        } else {
            return None;
        };
    let days_in_month = days_in_month(year, month)?;
    ((1..=days_in_month).contains(&day) && (1000..10000).contains(&year)).then(|| ReadDate {
        iso: format!("{year:04}-{month:02}-{day:02}T{time}{zone}"),
        assumed,
    })
}

/// Days of `month` (1-12) in the Gregorian `year`; None for no month.
fn days_in_month(year: u32, month: u32) -> Option<u32> {
    match month {
        1 | 3 | 5 | 7 | 8 | 10 | 12 => Some(31),
        4 | 6 | 9 | 11 => Some(30),
        2 if year.is_multiple_of(4) && (!year.is_multiple_of(100) || year.is_multiple_of(400)) => {
            Some(29)
        }
        2 => Some(28),
        _ => None,
    }
}

/// [`read_date`] for text already in ISO 8601 / RFC 3339.
fn iso8601_as_is(t: &str) -> Option<String> {
    let b = t.as_bytes();
    let digits = |r: std::ops::Range<usize>| {
        b.get(r.clone())
            .is_some_and(|s| s.iter().all(u8::is_ascii_digit))
    };
    if !(digits(0..4)
        && b.get(4) == Some(&b'-')
        && digits(5..7)
        && b.get(7) == Some(&b'-')
        && digits(8..10))
    {
        return None;
    }
    let (year, month, day): (u32, u32, u32) = (
        t[..4].parse().ok()?,
        t[5..7].parse().ok()?,
        t[8..10].parse().ok()?,
    );
    let days_in_month = days_in_month(year, month)?;
    if !(1..=days_in_month).contains(&day) {
        return None;
    }
    if b.len() == 10 {
        return Some(format!("{t}T00:00:00"));
    }
    if !matches!(b.get(10), Some(b'T' | b't' | b' '))
        || !digits(11..13)
        || b.get(13) != Some(&b':')
        || !digits(14..16)
    {
        return None;
    }
    let (h, m): (u32, u32) = (t[11..13].parse().ok()?, t[14..16].parse().ok()?);
    if h > 23 || m > 59 {
        return None;
    }
    let rest = &t[16..];
    let (seconds, zone) = match rest.strip_prefix(':') {
        Some(r) if r.len() >= 2 && r[..2].bytes().all(|c| c.is_ascii_digit()) => {
            let frac_end = r[2..]
                .find(|c: char| !(c.is_ascii_digit() || c == '.'))
                .map_or(r.len(), |k| k + 2);
            (&r[..frac_end], &r[frac_end..])
        }
        Some(_) => return None,
        None => ("00", rest),
    };
    if seconds[..2].parse::<u32>().ok()? > 60
        || (seconds.len() > 2 && (seconds.as_bytes()[2] != b'.' || seconds.len() == 3))
        || seconds[2..].matches('.').count() > 1
    {
        return None;
    }
    let zone = match zone.trim() {
        "" => String::new(),
        z => zone_of(z)?,
    };
    Some(format!("{}T{}:{seconds}{zone}", &t[..10], &t[11..16]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_forms_read() {
        for (text, want, assumed) in [
            ("2023-03-10 16:35:59", Some("2023-03-10T16:35:59"), false),
            ("2023-03-10T16:35:59Z", Some("2023-03-10T16:35:59Z"), false),
            (
                "2023-03-10T16:35:59.123+01:00",
                Some("2023-03-10T16:35:59.123+01:00"),
                false,
            ),
            ("2023-03-10t16:35:59z", Some("2023-03-10T16:35:59Z"), false),
            (
                "2023-03-10T16:35:59+0100",
                Some("2023-03-10T16:35:59+01:00"),
                false,
            ),
            (
                "2023-03-10T16:35-05",
                Some("2023-03-10T16:35:00-05:00"),
                false,
            ),
            (
                "Fri Mar 10 16:35:59 2023",
                Some("2023-03-10T16:35:59"),
                false,
            ),
            (
                "Fri, 10 Mar 2023 16:35:59 +0100",
                Some("2023-03-10T16:35:59+01:00"),
                false,
            ),
            ("10/03/2023 16:35", Some("2023-03-10T16:35:00"), true),
            ("13/03/2023 16:35", Some("2023-03-13T16:35:00"), false),
            ("03/13/2023", Some("2023-03-13T00:00:00"), false),
            ("3/10/2023 4:35:59 PM", Some("2023-03-10T16:35:59"), true),
            ("12/12/2023 12:05 AM", Some("2023-12-12T00:05:00"), false),
            ("10-03-2023 16:35", Some("2023-03-10T16:35:00"), true),
            ("10.03.2023", Some("2023-03-10T00:00:00"), false),
            ("29.02.2023", None, false),
            ("29.02.2024", Some("2024-02-29T00:00:00"), false),
            ("2023-02-30", None, false),
            ("2023-03-10T25:00", None, false),
            ("10/03/23", None, false),
            ("10/03-2023", None, false),
            ("16:35 PM 10/03/2023", None, false),
            ("2023-03-10T16:35:59+25:00", None, false),
            ("2023-03-10T16:35:59 nonsense", None, false),
        ] {
            let got = read_date(text);
            assert_eq!(got.as_ref().map(|d| d.iso.as_str()), want, "{text:?}");
            if let Some(d) = got {
                assert_eq!(d.assumed.is_some(), assumed, "{text:?}: {:?}", d.assumed);
            }
        }
    }
}
