//! Typed parameters from text: serde `deserialize_with` functions for a choice that a graph
//! file writes as text and its type parses with its own [`FromStr`] (the one parser the
//! node, the verbs' flags and Python share), so a node's config holds the parsed value, never
//! the string. A refusal is the parser's message; `surfstream_runtime::graph`'s
//! `params_from_table` prefixes the key it came from.

use std::fmt::Display;
use std::str::FromStr;

use serde::{Deserialize, Deserializer};

/// `#[serde(deserialize_with = "surfstream_core::choice::from_text")]`: a `T` from its text.
pub fn from_text<'de, D, T>(d: D) -> Result<T, D::Error>
where
    D: Deserializer<'de>,
    T: FromStr,
    T::Err: Display,
{
    let text = String::deserialize(d)?;
    text.parse().map_err(serde::de::Error::custom)
}

/// As [`from_text`], for an optional field (absent stays `None`; pair with `default`).
pub fn from_text_opt<'de, D, T>(d: D) -> Result<Option<T>, D::Error>
where
    D: Deserializer<'de>,
    T: FromStr,
    T::Err: Display,
{
    match Option::<String>::deserialize(d)? {
        None => Ok(None),
        Some(text) => text.parse().map(Some).map_err(serde::de::Error::custom),
    }
}

/// A choice that a graph file may write as a number or as text (`level = 6`, `level =
/// "auto"`): the number's decimal text, or the text, parsed by `T`'s [`FromStr`].
pub fn from_number_or_text<'de, D, T>(d: D) -> Result<T, D::Error>
where
    D: Deserializer<'de>,
    T: FromStr,
    T::Err: Display,
{
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum NumberOrText {
        Number(i64),
        Text(String),
    }
    let text = match NumberOrText::deserialize(d)? {
        NumberOrText::Number(n) => n.to_string(),
        NumberOrText::Text(t) => t,
    };
    text.parse().map_err(serde::de::Error::custom)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, PartialEq)]
    struct Even(u32);

    impl FromStr for Even {
        type Err = String;
        fn from_str(s: &str) -> Result<Self, String> {
            match s.trim().parse::<u32>() {
                Ok(n) if n % 2 == 0 => Ok(Even(n)),
                _ => Err(format!("{s:?}: expected an even number")),
            }
        }
    }

    #[derive(Debug, Deserialize)]
    struct Config {
        #[serde(deserialize_with = "from_text")]
        a: Even,
        #[serde(default, deserialize_with = "from_text_opt")]
        b: Option<Even>,
        #[serde(deserialize_with = "from_number_or_text")]
        c: Even,
    }

    #[test]
    fn a_choice_is_parsed_by_its_own_parser_and_refused_with_its_message() {
        let c: Config = serde_json::from_str(r#"{"a": " 4", "c": 6}"#).unwrap();
        assert_eq!((c.a, c.b, c.c), (Even(4), None, Even(6)));
        let c: Config = serde_json::from_str(r#"{"a": "2", "b": "8", "c": "10"}"#).unwrap();
        assert_eq!((c.b, c.c), (Some(Even(8)), Even(10)));
        let e = serde_json::from_str::<Config>(r#"{"a": "3", "c": 2}"#).unwrap_err();
        assert!(
            e.to_string().contains("\"3\": expected an even number"),
            "{e}"
        );
        let e = serde_json::from_str::<Config>(r#"{"a": "2", "c": 7}"#).unwrap_err();
        assert!(
            e.to_string().contains("\"7\": expected an even number"),
            "{e}"
        );
    }
}
