//! Whether a prompt names one of the action families a model was trained on (the demo model
//! records them, see `flame::assemble::ACTIONS_KEY`). A deliberately simple test, used only for
//! a note on stderr: the prompt's words (lower case, letters only) against each family's words
//! (`raise_arms` → `raise`, `arms` and `raisearms`) and their regular inflections (`-s`, `-es`,
//! `-ed`, `-d`, `-ing`, a doubled final consonant as in `running`, a dropped final `e` as in
//! `waving`). Synonyms the corpus also uses (`jog`, `stroll`, ...) are not known here.

/// The demo corpus's action families in table order (`flame_demo::Family::ALL`'s names, which the
/// runtime does not link): what `flame assemble --demo-actions` records. tests/cli.rs and
/// tests/assemble.rs check that the two lists agree.
pub const DEMO_FAMILIES: [&str; 15] = [
    "walk",
    "run",
    "jump",
    "hop",
    "wave",
    "clap",
    "punch",
    "kick",
    "squat",
    "crouch",
    "turn",
    "raise_arms",
    "bow",
    "side_step",
    "stand",
];

/// Whether `prompt` has a word that is one of `actions` or an inflection of it.
pub fn mentions_any(prompt: &str, actions: &[String]) -> bool {
    let keywords: Vec<String> = actions
        .iter()
        .flat_map(|a| {
            let lower = a.to_ascii_lowercase();
            let mut k: Vec<String> = lower.split('_').map(str::to_string).collect();
            if k.len() > 1 {
                k.push(lower.replace('_', ""));
            }
            k
        })
        .filter(|k| !k.is_empty())
        .collect();
    prompt
        .to_lowercase()
        .split(|c: char| !c.is_alphabetic())
        .filter(|w| !w.is_empty())
        .any(|w| keywords.iter().any(|k| inflects(w, k)))
}

/// Whether `word` is `stem` with one regular English ending.
fn inflects(word: &str, stem: &str) -> bool {
    let Some(rest) = word.strip_prefix(stem.trim_end_matches('e')) else {
        return false;
    };
    let dropped_e = stem.len() - stem.trim_end_matches('e').len();
    let last = stem.chars().last().unwrap_or_default();
    let endings = ["", "s", "es", "ed", "d", "ing"];
    // `rest` follows the stem without its final e's: put them back, or double the last letter.
    let full = &stem[stem.len() - dropped_e..];
    if let Some(end) = rest.strip_prefix(full) {
        if endings.contains(&end) {
            return true;
        }
    }
    if dropped_e > 0 && (rest == "ing" || rest == "ed") {
        return true;
    }
    rest.strip_prefix(last)
        .is_some_and(|end| dropped_e == 0 && (end == "ing" || end == "ed"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn demo() -> Vec<String> {
        DEMO_FAMILIES.iter().map(|f| f.to_string()).collect()
    }

    #[test]
    fn inflected_family_words_are_found() {
        for p in [
            "a person walks forward",
            "someone is running in a circle",
            "a man hops on one leg",
            "the woman is waving her right hand",
            "a figure waved",
            "he claps twice",
            "a person sidesteps to the left",
            "someone raises both arms",
            "a person jumped.",
            "Kicking high!",
            "a person bows",
        ] {
            assert!(mentions_any(p, &demo()), "{p}");
        }
    }

    #[test]
    fn prompts_outside_the_families_are_not() {
        for p in [
            "a person plays the guitar",
            "someone swims",
            "a person is dancing",
            "an elbow",
            "a runner",
            "",
        ] {
            assert!(!mentions_any(p, &demo()), "{p}");
        }
    }
}
