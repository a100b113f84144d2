//! Descriptions of corpus motions: each motion gets several sentences drawn from templates —
//! many subjects, verbs and synonyms, detail in different places (pace, limb, direction,
//! repetitions, size), present simple and progressive, and for two-action motions the usual
//! ways of saying "then".
//!
//! A verb-phrase template marks its verbs with braces (`{walk} forward`); `conjugate` turns
//! each into the third person (`walks`) or the `-ing` form (`walking`). `{pos}` becomes the
//! subject's possessive (his, her, their).

use super::actions::{Detail, Dice, Pace, Side, Size};
use super::family::Family;

/// Verb form a template is rendered in.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Form {
    Third,
    Ing,
}

const SUBJECTS: [(&str, &str); 18] = [
    ("a person", "their"),
    ("a person", "their"),
    ("someone", "their"),
    ("the person", "their"),
    ("a man", "his"),
    ("the man", "his"),
    ("a woman", "her"),
    ("the woman", "her"),
    ("a guy", "his"),
    ("a figure", "its"),
    ("the figure", "its"),
    ("a human", "their"),
    ("an individual", "their"),
    ("a character", "their"),
    ("the character", "their"),
    ("a boy", "his"),
    ("a girl", "her"),
    ("the subject", "their"),
];

/// Verbs whose final consonant doubles before `-ing`.
const DOUBLING: [&str; 14] = [
    "run", "hop", "step", "jog", "clap", "get", "put", "jab", "stop", "skip", "scan", "drop",
    "spin", "sidestep",
];

/// `walk` → `walks` / `walking`, with the spelling rules the vocabulary needs.
fn conjugate(verb: &str, form: Form) -> String {
    match form {
        Form::Third => {
            if verb == "do"
                || verb == "go"
                || ["s", "x", "z", "ch", "sh"]
                    .iter()
                    .any(|e| verb.ends_with(e))
            {
                format!("{verb}es")
            } else {
                format!("{verb}s")
            }
        }
        Form::Ing => {
            if DOUBLING.contains(&verb) {
                let last = &verb[verb.len() - 1..];
                format!("{verb}{last}ing")
            } else if verb.ends_with('e') && !verb.ends_with("ee") && verb != "be" {
                format!("{}ing", &verb[..verb.len() - 1])
            } else {
                format!("{verb}ing")
            }
        }
    }
}

/// Renders a template in `form` with `pos` as the possessive.
fn render(template: &str, form: Form, pos: &str) -> String {
    let mut out = String::new();
    let mut rest = template;
    while let Some(i) = rest.find('{') {
        out.push_str(&rest[..i]);
        let j = rest[i..].find('}').map(|j| i + j).unwrap_or(rest.len() - 1);
        let word = &rest[i + 1..j];
        if word == "pos" {
            out.push_str(pos);
        } else {
            out.push_str(&conjugate(word, form));
        }
        rest = &rest[j + 1..];
    }
    out.push_str(rest);
    out.split_whitespace().collect::<Vec<_>>().join(" ")
}

fn number(n: usize) -> &'static str {
    [
        "zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten",
    ]
    .get(n)
    .copied()
    .unwrap_or("many")
}

/// "once", "twice", "three times", or a vaguer synonym.
fn times(n: usize, d: &mut Dice) -> String {
    let exact = match n {
        1 => "once".to_string(),
        2 => "twice".to_string(),
        _ => format!("{} times", number(n)),
    };
    if n >= 3 && d.chance(0.35) {
        return d
            .pick(&[
                "several times",
                "a few times",
                "repeatedly",
                "multiple times",
            ])
            .to_string();
    }
    if n == 2 && d.chance(0.2) {
        return "two times".to_string();
    }
    exact
}

fn pace_adverb(pace: Option<Pace>, d: &mut Dice) -> &'static str {
    match pace {
        Some(Pace::Slow) => d.pick(&[
            "slowly",
            "slowly",
            "at a slow pace",
            "leisurely",
            "at a leisurely pace",
            "unhurriedly",
            "calmly",
        ]),
        Some(Pace::Fast) => d.pick(&[
            "quickly",
            "quickly",
            "fast",
            "rapidly",
            "briskly",
            "at a fast pace",
            "hurriedly",
        ]),
        _ => d.pick(&[
            "",
            "",
            "",
            "at a normal pace",
            "at a steady pace",
            "casually",
        ]),
    }
}

fn side_word(s: Side) -> &'static str {
    match s {
        Side::Left => "left",
        Side::Right => "right",
        Side::Both => "both",
        Side::Alternate => "alternating",
    }
}

fn size_adverb(size: Option<Size>, d: &mut Dice) -> &'static str {
    match size {
        Some(Size::Small) => d.pick(&["a little", "slightly", "gently", ""]),
        Some(Size::Large) => d.pick(&["high", "very high", "energetically", ""]),
        _ => "",
    }
}

/// Verb-phrase templates for one action (several are picked per motion).
fn phrases(x: &Detail, d: &mut Dice) -> Vec<String> {
    let pace = pace_adverb(x.pace, d);
    let dir = x.direction.map(side_word).unwrap_or("left");
    let limb = x.limb.map(side_word).unwrap_or("right");
    let n = x.count.unwrap_or(1);
    let t = times(n, d);
    let mut v: Vec<String> = Vec::new();
    let mut add = |s: String| v.push(s);
    match x.family {
        Family::Walk => match x.variant.as_str() {
            "backward" => {
                for s in [
                    format!("{{walk}} backward {pace}"),
                    format!("{{walk}} backwards {pace}"),
                    format!("{pace} {{step}} backwards"),
                    format!("{{move}} backward {pace}"),
                    format!("{{back}} up {pace}"),
                    format!("{{walk}} in reverse {pace}"),
                    "{take} several steps backward".into(),
                    format!("{{retreat}} {pace} walking backwards"),
                    "{walk} back without turning around".into(),
                ] {
                    add(s);
                }
            }
            "forward" => {
                for s in [
                    format!("{{walk}} forward {pace}"),
                    format!("{{walk}} {pace} forward"),
                    format!("{{walk}} straight ahead {pace}"),
                    format!("{{stroll}} forward {pace}"),
                    format!("{{walk}} forwards {pace}"),
                    format!("{{move}} forward {pace}"),
                    format!("{{take}} a few steps forward {pace}"),
                    format!("{{walk}} in a straight line {pace}"),
                    format!("{{walk}} ahead {pace}"),
                    format!("{{advance}} {pace} on foot"),
                    format!("{{go}} for a walk {pace}"),
                    format!("{{walk}} {pace}"),
                    format!("{{step}} forward {pace}"),
                ] {
                    add(s);
                }
                if x.pace == Some(Pace::Slow) {
                    add("{stroll} along".into());
                    add("{amble} forward".into());
                }
                if x.pace == Some(Pace::Fast) {
                    add("{walk} briskly ahead".into());
                    add("{rush} forward on foot".into());
                }
            }
            _ => {
                let deg = x.degrees.unwrap_or(90);
                for s in [
                    format!("{{walk}} in a curve to the {dir} {pace}"),
                    format!("{{walk}} forward while turning {dir}"),
                    format!("{{walk}} along a curved path to the {dir}"),
                    format!("{{walk}} in an arc toward the {dir} {pace}"),
                    format!("{{curve}} to the {dir} while walking"),
                    format!("{{walk}} and gradually {{turn}} {dir}"),
                    format!("{{walk}} around to the {dir} {pace}"),
                    format!("{{veer}} to the {dir} while walking"),
                ] {
                    add(s);
                }
                if deg >= 150 {
                    add(format!("{{walk}} in a half circle to the {dir}"));
                    add(format!("{{walk}} in a u-turn to the {dir}"));
                } else {
                    add(format!("{{walk}} forward and {{bear}} {dir}"));
                }
            }
        },
        Family::Run => {
            let curve = x.variant == "curve";
            let way = if curve {
                format!("in a curve to the {dir}")
            } else {
                d.pick(&["forward", "ahead", "straight ahead", "forward", ""])
                    .to_string()
            };
            match x.pace {
                Some(Pace::Slow) => {
                    add(format!("{{jog}} {way}"));
                    add(format!("{{jog}} {way} at an easy pace"));
                    add(format!("{{run}} {way} slowly"));
                    add(format!("{{go}} for a jog {way}"));
                    add(format!("{{jog}} lightly {way}"));
                }
                Some(Pace::Fast) => {
                    add(format!("{{sprint}} {way}"));
                    add(format!("{{run}} {way} very fast"));
                    add(format!("{{dash}} {way}"));
                    add(format!("{{run}} quickly {way}"));
                    add(format!("{{race}} {way} at full speed"));
                }
                _ => {
                    add(format!("{{run}} {way}"));
                    add(format!("{{jog}} {way}"));
                }
            }
            for s in [
                format!("{{run}} {way}"),
                format!("{{run}} {way} {pace}"),
                format!("{{start}} running {way}"),
                format!("{{break}} into a run {way}"),
                format!("{{run}} {way} on foot"),
            ] {
                add(s);
            }
            if curve {
                add(format!("{{run}} and {{turn}} {dir}"));
                add(format!("{{run}} along a curve bending {dir}"));
            }
        }
        Family::Jump => {
            let high = size_adverb(x.size, d);
            match x.variant.as_str() {
                "forward" => {
                    for s in [
                        format!("{{jump}} forward {t}"),
                        format!("{{leap}} forward {t}"),
                        format!("{{jump}} ahead with both feet {t}"),
                        "{do} a long jump forward".to_string(),
                        format!("{{jump}} forward {high}"),
                        "{make} a standing jump forward".to_string(),
                        format!("{{jump}} forwards {t}"),
                        format!("{{leap}} ahead {t}"),
                    ] {
                        add(s);
                    }
                    if n > 1 {
                        add(format!("{{do}} {} jumps forward", number(n)));
                        add("{jump} forward again and again".into());
                    }
                }
                _ => {
                    for s in [
                        format!("{{jump}} in place {t}"),
                        format!("{{jump}} up {high} {t}"),
                        format!("{{jump}} straight up {t}"),
                        format!("{{leap}} into the air {t}"),
                        format!("{{jump}} on the spot {t}"),
                        format!("{{jump}} {t}"),
                        format!("{{jump}} vertically {t}"),
                        format!("{{jump}} {high} in the air"),
                    ] {
                        add(s);
                    }
                    if n == 1 {
                        add("{do} a jump".into());
                        add("{do} a vertical jump".into());
                        add("{jump} up once and {land}".into());
                    } else {
                        add("{jump} up and down".into());
                        add(format!("{{do}} {} jumps in place", number(n)));
                        add("{keep} jumping in place".into());
                        add(format!("{{jump}} repeatedly {high}"));
                    }
                }
            }
        }
        Family::Hop => {
            let way = if x.variant == "forward" {
                "forward"
            } else {
                d.pick(&["in place", "on the spot", ""])
            };
            let other = if limb == "left" { "right" } else { "left" };
            for s in [
                format!("{{hop}} on {{pos}} {limb} foot {way}"),
                format!("{{hop}} on the {limb} leg {way}"),
                format!("{{hop}} {way} on one foot"),
                format!("{{hop}} on one leg {way} {t}"),
                format!("{{hop}} {t} on the {limb} foot"),
                format!("{{lift}} the {other} leg and {{hop}} on the {limb} {way}"),
                format!("{{stand}} on the {limb} leg and {{hop}} {way}"),
                format!("{{bounce}} on {{pos}} {limb} foot {way}"),
                format!("{{do}} one-legged hops {way}"),
                format!("{{hop}} on a single leg {way}"),
            ] {
                add(s);
            }
        }
        Family::Wave => {
            let hand = match x.limb {
                Some(Side::Both) => d
                    .pick(&["both hands", "both arms", "both of {pos} hands"])
                    .to_string(),
                _ => d
                    .pick(&["{pos} LIMB hand", "the LIMB hand", "{pos} LIMB arm"])
                    .replace("LIMB", limb),
            };
            let how = size_adverb(x.size, d);
            for s in [
                format!("{{wave}} {hand}"),
                format!("{{wave}} with {hand}"),
                format!("{{wave}} {hand} {how}"),
                format!("{{raise}} {hand} and {{wave}}"),
                format!("{{wave}} hello with {hand}"),
                format!("{{wave}} goodbye with {hand}"),
                format!("{{wave}} {hand} in greeting"),
                format!("{{greet}} someone by waving {hand}"),
                format!("{{wave}} at someone with {hand} {t}"),
                format!("{{wave}} {hand} back and forth"),
                format!("{{lift}} {hand} up and {{wave}} {pace}"),
            ] {
                add(s);
            }
            if x.limb == Some(Side::Both) {
                add("{wave} with both hands above the shoulders".into());
            } else {
                add(format!("{{wave}} using the {limb} hand"));
            }
        }
        Family::Clap => {
            for s in [
                format!("{{clap}} {{pos}} hands {t}"),
                format!("{{clap}} {t}"),
                format!("{{clap}} {pace}"),
                format!("{{clap}} {{pos}} hands {pace}"),
                format!("{{applaud}} {pace}"),
                format!("{{clap}} {{pos}} hands together {t}"),
                "{give} a round of applause".into(),
                "{clap} in front of {pos} chest".into(),
                format!("{{bring}} {{pos}} hands together {t}"),
                format!("{{clap}} {pace} in front of the body"),
                format!("{{do}} {} claps", number(n)),
            ] {
                add(s);
            }
            if n > 2 {
                add("{clap} repeatedly".into());
                add("{keep} clapping".into());
            }
        }
        Family::Punch => {
            let seq: Vec<&str> = x.sequence.iter().map(|&s| side_word(s)).collect();
            match x.limb {
                Some(Side::Alternate) => {
                    let combo = seq.join(", ");
                    for s in [
                        format!("{{punch}} {combo}"),
                        format!("{{throw}} a {} combination", seq.join("-")),
                        format!("{{throw}} punches with both fists {pace}"),
                        format!("{{punch}} with alternating fists {t}"),
                        format!("{{punch}} the air {t} alternating hands"),
                        format!("{{throw}} a combo of {} punches", number(n)),
                        "{shadowbox}".into(),
                        format!("{{box}} {pace} with both hands"),
                        format!(
                            "{{throw}} {} punches with the {} and {} hand",
                            number(n),
                            seq[0],
                            if seq[0] == "left" { "right" } else { "left" }
                        ),
                        format!("{{do}} a boxing combo, {combo}"),
                    ] {
                        add(s);
                    }
                }
                _ => {
                    let fist = d.pick(&["fist", "hand", "arm"]);
                    let a = if n == 1 { "a" } else { number(n) };
                    let punches = if n == 1 { "punch" } else { "punches" };
                    for s in [
                        format!("{{punch}} with {{pos}} {limb} {fist} {t}"),
                        format!("{{punch}} forward with the {limb} {fist}"),
                        format!("{{throw}} {a} {limb} {punches}"),
                        format!("{{throw}} {a} {punches} with the {limb} hand"),
                        format!("{{punch}} {t} using the {limb} {fist}"),
                        format!("{{strike}} forward with {{pos}} {limb} {fist}"),
                        format!("{{punch}} the air with the {limb} {fist} {pace}"),
                        format!("{{jab}} with the {limb} hand {t}"),
                        format!("{{throw}} {limb} jabs {pace}"),
                        format!("{{punch}} straight ahead with the {limb} {fist}"),
                    ] {
                        add(s);
                    }
                }
            }
        }
        Family::Kick => {
            let high = size_adverb(x.size, d);
            let leg = d.pick(&["leg", "foot"]);
            for s in [
                format!("{{kick}} with the {limb} {leg} {t}"),
                format!("{{kick}} forward with {{pos}} {limb} {leg}"),
                format!("{{kick}} {high} with the {limb} {leg}"),
                format!("{{do}} a front kick with the {limb} {leg}"),
                format!("{{kick}} the {limb} {leg} out in front {t}"),
                format!("{{throw}} a {limb} kick {t}"),
                format!("{{perform}} a kick with {{pos}} {limb} {leg}"),
                format!("{{kick}} {t} using the {limb} {leg}"),
                format!("{{kick}} the air with the {limb} {leg}"),
                format!("{{lift}} the {limb} knee and {{kick}} forward"),
            ] {
                add(s);
            }
        }
        Family::Squat => {
            let arms = match x.variant.as_str() {
                "forward" => d.pick(&[
                    "with arms stretched out in front",
                    "with both arms held forward",
                    "extending the arms forward",
                    "",
                ]),
                "hips" => d.pick(&["with hands on the hips", "with hands on {pos} hips", ""]),
                _ => "",
            };
            let deep = if x.size == Some(Size::Large) {
                d.pick(&["deep", "low", ""])
            } else {
                ""
            };
            for s in [
                format!("{{do}} {deep} squats {arms}"),
                format!("{{squat}} {t} {arms}"),
                format!("{{do}} {} {deep} squats", number(n)),
                format!("{{perform}} {} squats {pace}", number(n)),
                format!("{{squat}} down and up {t}"),
                format!("{{do}} a set of squats {arms}"),
                format!("{{squat}} repeatedly {pace}"),
                format!("{{bend}} {{pos}} knees {t} doing squats"),
                format!("{{do}} {} knee bends", number(n)),
                format!("{{exercise}} by squatting {t}"),
                format!("{{squat}} {pace} {t}"),
            ] {
                add(s);
            }
        }
        Family::Crouch => {
            for s in [
                "{crouch} down and {stand} back up".to_string(),
                format!("{{crouch}} down {pace} then {{get}} up"),
                "{crouch} low for a moment before standing up".into(),
                "{get} down into a crouch and then {stand} up".into(),
                format!("{{lower}} {{pos}} body into a crouch and {{rise}} again {pace}"),
                "{duck} down low and then {stand} up again".into(),
                "{hunker} down and then {get} back up".into(),
                "{bend} the knees deeply, {stay} low, and {come} back up".into(),
                format!("{{crouch}} {pace}, {{hold}} it, and {{stand}}"),
                "{drop} into a low crouch and {return} to standing".into(),
            ] {
                add(s);
            }
        }
        Family::Turn => {
            let deg = x.degrees.unwrap_or(180);
            let amount = match deg {
                90 => d.pick(&["ninety degrees", "90 degrees", "a quarter turn"]),
                180 => d.pick(&[
                    "around",
                    "180 degrees",
                    "a half turn",
                    "to face the other way",
                ]),
                270 => d.pick(&[
                    "270 degrees",
                    "three quarters of a turn",
                    "three quarters around",
                ]),
                _ => d.pick(&[
                    "a full circle",
                    "all the way around",
                    "360 degrees",
                    "in a full turn",
                ]),
            };
            for s in [
                format!("{{turn}} {amount} to the {dir}"),
                format!("{{turn}} {dir} {amount} in place"),
                format!("{{turn}} to the {dir} {pace}"),
                format!("{{turn}} {amount} on the spot"),
                format!("{{rotate}} {amount} to the {dir}"),
                format!("{{turn}} around in place to the {dir}"),
                format!("{{pivot}} to the {dir} {pace}"),
                format!("{{spin}} {amount} {pace}"),
                format!("{{turn}} {{pos}} body {amount}"),
                format!("{{step}} around in place, turning {dir}"),
            ] {
                add(s);
            }
            if deg == 180 {
                add("{turn} around to face the opposite direction".into());
                add("{turn} around and {face} the other way".into());
            }
            if deg == 360 {
                add(format!("{{turn}} in a complete circle to the {dir}"));
            }
        }
        Family::RaiseArms => {
            let many = if n > 1 { t.as_str() } else { "" };
            for s in [
                format!("{{raise}} both arms {many}"),
                format!("{{raise}} {{pos}} arms above {{pos}} head {many}"),
                format!("{{lift}} both hands overhead {pace}"),
                format!("{{put}} {{pos}} hands up {many}"),
                format!("{{raise}} {{pos}} hands in the air {many}"),
                format!("{{stretch}} {{pos}} arms up {pace}"),
                "{reach} up toward the sky with both arms".into(),
                "{hold} both arms up over {pos} head".to_string(),
                format!("{{lift}} the arms up and {{lower}} them {t}"),
                format!("{{throw}} both hands up {many}"),
                format!("{{raise}} the arms overhead {pace}"),
            ] {
                add(s);
            }
        }
        Family::Bow => {
            let how = match x.size {
                Some(Size::Small) => d.pick(&["slightly", "a little", "briefly"]),
                Some(Size::Large) => d.pick(&["deeply", "low", "very deeply"]),
                _ => d.pick(&["politely", "respectfully", ""]),
            };
            let many = if n > 1 { "twice" } else { "" };
            for s in [
                format!("{{bow}} {how} {many}"),
                format!("{{bow}} down {how}"),
                format!("{{take}} a bow {many}"),
                format!("{{bow}} {pace} {many}"),
                format!("{{bend}} forward at the waist {how}"),
                format!(
                    "{{give}} a {} bow",
                    if how.is_empty() { "polite" } else { "small" }
                ),
                format!("{{lean}} forward in a bow {many}"),
                format!("{{bow}} {how} to someone in front"),
                format!("{{bow}} {many} and {{straighten}} up"),
                "{bow} to the audience".into(),
            ] {
                add(s);
            }
        }
        Family::SideStep => {
            let k = number(n);
            for s in [
                format!("{{sidestep}} to the {dir}"),
                format!("{{step}} sideways to the {dir} {pace}"),
                format!("{{walk}} sideways to the {dir}"),
                format!("{{shuffle}} to the {dir}"),
                format!("{{move}} sideways to the {dir} {pace}"),
                format!("{{take}} {k} steps to the {dir}"),
                format!("{{take}} {k} side steps to the {dir}"),
                format!("{{do}} side steps to the {dir} {t}"),
                format!("{{step}} to the {dir} side {pace}"),
                format!("{{shuffle}} sideways toward the {dir}"),
                format!("{{move}} laterally to the {dir}"),
            ] {
                add(s);
            }
        }
        Family::Stand => {
            if x.variant == "look_around" {
                for s in [
                    "{look} around",
                    "{stand} and {look} around",
                    "{look} left and right",
                    "{turn} {pos} head to look around",
                    "{glance} around",
                    "{look} from side to side",
                    "{stand} in place looking around",
                    "{look} around curiously",
                    "{stand} still while looking around",
                    "{scan} the surroundings",
                    "{look} to the left and to the right",
                ] {
                    add(s.into());
                }
            } else {
                for s in [
                    "{stand} still",
                    "{stand} in place",
                    "{stand} without moving",
                    "{stay} still",
                    "{remain} standing",
                    "{stand} idle",
                    "{stand} quietly",
                    "{wait} in place",
                    "{stand} there doing nothing",
                    "{stand} upright and still",
                    "{stand} calmly",
                ] {
                    add(s.into());
                }
            }
        }
    }
    v
}

/// One verb phrase for an action, in `form`.
fn phrase(x: &Detail, d: &mut Dice, form: Form, pos: &str) -> String {
    let options = phrases(x, d);
    render(&options[d.int(0, options.len() - 1)], form, pos)
}

/// One sentence for the actions of a motion.
fn sentence(actions: &[Detail], d: &mut Dice) -> String {
    let (subject, pos) = d.pick(&SUBJECTS);
    let third = |d: &mut Dice, x: &Detail| phrase(x, d, Form::Third, pos);
    let ing = |d: &mut Dice, x: &Detail| phrase(x, d, Form::Ing, pos);
    let s = if actions.len() == 1 {
        let x = &actions[0];
        match d.int(0, 9) {
            0..=4 => format!("{subject} {}", third(d, x)),
            5 | 6 => format!("{subject} is {}", ing(d, x)),
            7 => format!("{subject} {}", ing(d, x)),
            8 => format!("{subject} {} {}", d.pick(&["starts", "begins"]), ing(d, x)),
            _ => format!(
                "{subject} {} and then {}",
                third(d, x),
                d.pick(&["stops", "comes to rest", "stands", "goes back to standing"])
            ),
        }
    } else {
        let (a, b) = (&actions[0], &actions[1]);
        match d.int(0, 8) {
            0 => format!("{subject} {} then {}", third(d, a), third(d, b)),
            1 => format!("{subject} {} and then {}", third(d, a), third(d, b)),
            2 => format!("{subject} {}, then {}", third(d, a), third(d, b)),
            3 => format!("first {subject} {}, then {}", third(d, a), third(d, b)),
            4 => format!("{subject} {} before {}", third(d, a), ing(d, b)),
            5 => format!("after {}, {subject} {}", ing(d, a), third(d, b)),
            6 => format!("{subject} {}, and afterwards {}", third(d, a), third(d, b)),
            7 => format!("{subject} {} followed by {}", third(d, a), ing(d, b)),
            _ => format!("{subject} {}, after that {}", third(d, a), third(d, b)),
        }
    };
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// At least `min` distinct sentences describing a motion made of `actions` (one or two).
pub fn describe(actions: &[Detail], d: &mut Dice, min: usize) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    let want = min + d.int(0, 3);
    for _ in 0..want * 20 {
        let s = sentence(actions, d);
        if !out.contains(&s) {
            out.push(s);
        }
        if out.len() >= want {
            break;
        }
    }
    out
}

/// Lowercase, punctuation removed, single spaces: the form prompts are compared in.
pub fn normalize(s: &str) -> String {
    s.to_lowercase()
        .chars()
        .map(|c| if c.is_alphanumeric() { c } else { ' ' })
        .collect::<String>()
        .split_whitespace()
        .collect::<Vec<_>>()
        .join(" ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn verbs_conjugate() {
        for (v, s, ing) in [
            ("walk", "walks", "walking"),
            ("run", "runs", "running"),
            ("wave", "waves", "waving"),
            ("punch", "punches", "punching"),
            ("do", "does", "doing"),
            ("box", "boxes", "boxing"),
            ("hop", "hops", "hopping"),
            ("see", "sees", "seeing"),
        ] {
            assert_eq!(conjugate(v, Form::Third), s);
            assert_eq!(conjugate(v, Form::Ing), ing);
        }
        assert_eq!(
            render("{raise} {pos} hand and {wave}", Form::Ing, "her"),
            "raising her hand and waving"
        );
    }
}
