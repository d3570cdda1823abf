//! Command-line choices: fieldless enums whose variants an option names by one word.
//!
//! The macro `choices!` (below) gives such an enum `FromStr` and `Display` from one list
//! of `Variant => "word"` pairs, so the words parsed and the words written back (in
//! `--help` defaults and in the JSON outputs that record them) cannot drift apart. An unknown word is an
//! [`crate::ErrorKind::Invalid`] error naming the option, the word and every word the
//! option takes.

/// `` `a` ``, `` `a` or `b` ``, `` `a`, `b` or `c` ``: the words an option takes.
pub fn one_of(words: &[&str]) -> String {
    let quoted: Vec<String> = words.iter().map(|w| format!("`{w}`")).collect();
    match quoted.split_last() {
        None => String::new(),
        Some((last, [])) => last.clone(),
        Some((last, rest)) => format!("{} or {last}", rest.join(", ")),
    }
}

/// Implements `FromStr` and `Display` for a fieldless enum, and the associated
/// `WORDS` (the words in the order given): `choices!(Spots, "--spots", Centred =>
/// "centred", Pinholes => "pinholes")`.
macro_rules! choices {
    ($ty:ident, $option:literal, $($variant:ident => $word:literal),+ $(,)?) => {
        impl $ty {
            /// The words the option takes, in the order of the variants.
            pub const WORDS: &'static [&'static str] = &[$($word),+];
        }

        impl std::str::FromStr for $ty {
            type Err = $crate::Error;
            fn from_str(s: &str) -> $crate::Result<$ty> {
                match s {
                    $($word => Ok($ty::$variant),)+
                    _ => Err($crate::Error::invalid(
                        $option,
                        format!("`{s}`: expected {}", $crate::choice::one_of($ty::WORDS)),
                    )),
                }
            }
        }

        impl std::fmt::Display for $ty {
            /// The word the option takes for this variant.
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(match self {
                    $($ty::$variant => $word,)+
                })
            }
        }
    };
}

#[cfg(test)]
mod tests {
    use super::one_of;

    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    enum Pick {
        Left,
        Middle,
        Right,
    }
    choices!(Pick, "--pick", Left => "left", Middle => "middle", Right => "right");

    #[test]
    fn words_parse_to_their_variants_and_display_back() {
        for (word, pick) in Pick::WORDS
            .iter()
            .zip([Pick::Left, Pick::Middle, Pick::Right])
        {
            assert_eq!(word.parse::<Pick>().unwrap(), pick);
            assert_eq!(pick.to_string(), *word);
        }
    }

    #[test]
    fn an_unknown_word_names_the_option_the_word_and_every_known_word() {
        let e = "up".parse::<Pick>().unwrap_err();
        let text = e.to_string();
        assert!(text.contains("--pick"), "{text}");
        assert!(
            text.contains("`up`: expected `left`, `middle` or `right`"),
            "{text}"
        );
        assert_eq!(e.kind, crate::ErrorKind::Invalid);
    }

    #[test]
    fn one_of_joins_with_commas_and_a_final_or() {
        assert_eq!(one_of(&[]), "");
        assert_eq!(one_of(&["a"]), "`a`");
        assert_eq!(one_of(&["a", "b"]), "`a` or `b`");
        assert_eq!(one_of(&["a", "b", "c"]), "`a`, `b` or `c`");
    }
}
