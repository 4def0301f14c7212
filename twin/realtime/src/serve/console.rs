//! Commands typed while `twin serve` runs (one per line on stdin): faults,
//! forced inputs, read-only, status. A line's words are read by clap as a
//! command line without a program name, so `help` lists the commands as
//! every `twin` subcommand's help does, and a mistake gets clap's words;
//! what clap cannot check (a word that is a code or a link's name) is
//! checked here. Run on the engine's thread.

use clap::{Parser, Subcommand};
use nodes::firmware::Refusal;
use nodes::link::{Junk, JunkBytes, JunkPlace, MAX_JUNK};
use protocols::time::SimDuration;
use std::io::BufRead;
use std::sync::mpsc::Sender;

use crate::forces::Input;
use crate::typed_line::{self, OnOff, Typed};
use crate::{Inbound, LinkFault, RtEngine};

/// What can be typed, one command a line.
#[derive(Debug, Parser)]
#[command(
    name = "console",
    no_binary_name = true,
    disable_help_flag = true,
    disable_version_flag = true,
    override_usage = "<COMMAND> [ARGS]...",
    help_template = "Commands, one a line (`help COMMAND` tells more of one):\n{subcommands}",
    max_term_width = 100
)]
enum Line {
    /// The module's state, clients, tick lateness
    Status,
    /// Open connections
    Clients,
    #[command(
        subcommand,
        about = "Spoil the replies of every link, or of one (`help fault` lists the faults)",
        long_about = "Spoil the replies of every link, or of one"
    )]
    Fault(Fault),
    #[command(
        about = "The controller measures VALUE on input NAME (`help force` lists them)",
        long_about = "The controller measures VALUE on input NAME, from its next loop tick",
        after_help = inputs_help()
    )]
    Force {
        /// One of the inputs below
        #[arg(value_parser = Input::parse)]
        name: Input,
        /// A number in the input's unit, or on|off
        #[arg(allow_negative_numbers = true)]
        value: String,
    },
    /// Measure input NAME again, or every input (`all`)
    Release {
        /// An input (`help force` lists them), or all
        #[arg(value_name = "NAME|all", value_parser = released)]
        name: Released,
    },
    /// Refuse writes from every client, or take them again
    #[command(name = "read-only")]
    ReadOnly {
        #[arg(value_enum, value_name = "on|off")]
        on: OnOff,
    },
    /// End the session (as SIGINT)
    #[command(alias = "quit", alias = "exit")]
    Stop,
}

/// The faults of `fault`; LINK is a link's name or protocol, every link
/// without it.
#[derive(Debug, Subcommand)]
#[command(
    disable_help_subcommand = true,
    after_help = "LINK is a link's name or protocol (meb, modbus-rtu, ...); without it, every link."
)]
enum Fault {
    /// Replies go out with their check value + 1 (MEB, RTU, modbus8)
    BadCheck {
        /// A link's name or protocol; every link without it
        link: Option<String>,
    },
    /// Requests are served but never answered
    NoReply {
        /// A link's name or protocol; every link without it
        link: Option<String>,
    },
    /// Replies go out MS milliseconds late (0-60000)
    Delay {
        #[arg(value_parser = delay_ms, allow_negative_numbers = true)]
        ms: f64,
        /// A link's name or protocol; every link without it
        link: Option<String>,
    },
    /// Every request refused: Modbus exception / MEB ER CODE (1-4, default 4; MEB and Modbus links, not --modbus8)
    Exception {
        /// 1 illegal function/command, 2 illegal address, 3 illegal data, 4 device failure
        code: Option<String>,
        /// A link's name or protocol; every link without it
        link: Option<String>,
    },
    /// Replies come from slave ID (default: the next id), check good (MEB, RTU, modbus8)
    WrongId {
        /// The id the replies carry
        id: Option<String>,
        /// A link's name or protocol; every link without it
        link: Option<String>,
    },
    /// Each reply in two writes, the second MS milliseconds after the first (0-10000)
    Split {
        #[arg(value_parser = split_ms, allow_negative_numbers = true)]
        ms: f64,
        /// A link's name or protocol; every link without it
        link: Option<String>,
    },
    /// N random bytes (or these, e.g. hex:00ff) before each reply (after it with `after`)
    Junk {
        /// How many random bytes, or these (hex:BYTES)
        #[arg(value_name = "N|hex:BYTES", value_parser = junk_bytes)]
        bytes: JunkBytes,
        /// Before the reply (the default), or after it: between it and the next request
        #[arg(value_name = "after|before")]
        place: Option<String>,
        /// A link's name or protocol; every link without it
        link: Option<String>,
    },
    /// No fault
    Off,
}

/// `release`'s input, `None` for all of them.
#[derive(Debug, Clone, Copy)]
struct Released(Option<Input>);

/// A parsed console command: what to run on the engine.
pub type Command = Box<dyn FnOnce(&mut RtEngine) + Send>;

/// Parses one line: `Ok(None)` for a blank one, `Err` the mistake to print.
pub fn parse(line: &str) -> Result<Option<Command>, String> {
    // `?` is help's other name, as it was before clap read the console.
    let line = match line.trim().strip_prefix('?') {
        Some(rest) if rest.is_empty() || rest.starts_with(' ') => format!("help{rest}"),
        _ => line.to_string(),
    };
    match typed_line::read::<Line>(&line)? {
        Typed::Blank => Ok(None),
        Typed::Help(text) => Ok(Some(Box::new(move |e: &mut RtEngine| e.say(text)))),
        Typed::Command(line) => command(line)
            .map(Some)
            .map_err(|why| format!("error: {why}")),
    }
}

/// What runs on the engine for `line`, or why it cannot.
fn command(line: Line) -> Result<Command, String> {
    Ok(match line {
        Line::Status => Box::new(|e: &mut RtEngine| {
            let line = e.status_line(e.clock.now());
            e.say(line);
        }),
        Line::Clients => Box::new(|e: &mut RtEngine| {
            let lines: Vec<String> = e
                .connections()
                .map(|(l, peer)| {
                    let name = e.links.get(l).map_or("?", |l| l.name.as_str());
                    format!("  {name} {peer}")
                })
                .collect();
            e.say(format!(
                "{} open connection(s)\n{}",
                lines.len(),
                lines.join("\n")
            ));
        }),
        Line::Stop => Box::new(|e: &mut RtEngine| {
            e.say("stopping");
            e.request_stop("console");
        }),
        Line::ReadOnly { on } => {
            let on = on.is_on();
            Box::new(move |e: &mut RtEngine| {
                e.set_read_only(on);
                e.say(format!("read-only {}", if on { "on" } else { "off" }));
            })
        }
        Line::Fault(fault) => {
            let Some((fault, link)) = link_fault(fault)? else {
                return Ok(Box::new(|e: &mut RtEngine| {
                    e.set_fault(None, None);
                    e.say("fault off");
                }));
            };
            Box::new(
                move |e: &mut RtEngine| match link_index(e, link.as_deref()) {
                    Ok(l) => {
                        e.set_fault(Some(fault), l);
                        let on = link.as_deref().unwrap_or("every link");
                        e.say(format!("fault {fault} on {on}"));
                    }
                    Err(why) => e.say(why),
                },
            )
        }
        Line::Force { name, value } => {
            let forced = name.value_text(&value).map_err(|e| e.to_string())?;
            let name = forced.input().name();
            Box::new(move |e: &mut RtEngine| {
                e.force(forced);
                e.say(format!("forced {name} = {forced}"));
            })
        }
        Line::Release {
            name: Released(input),
        } => Box::new(move |e: &mut RtEngine| {
            for d in &mut e.devices {
                match input {
                    Some(input) => d.forces.release(input),
                    None => d.forces = Default::default(),
                }
            }
            e.say(format!("released {}", input.map_or("all", |i| i.name())));
        }),
    })
}

/// A fault and the link it is for, its optional words told apart: a
/// code or an id is a number, `after` and `before` are places, any other
/// word is a link's name. `None` for `fault off`.
fn link_fault(fault: Fault) -> Result<Option<(LinkFault, Option<String>)>, String> {
    Ok(Some(match fault {
        Fault::BadCheck { link } => (LinkFault::BadCheck, link),
        Fault::NoReply { link } => (LinkFault::NoReply, link),
        Fault::Delay { ms, link } => (
            LinkFault::Delay(SimDuration::from_secs_f64(ms / 1000.0)),
            link,
        ),
        Fault::Split { ms, link } => (
            LinkFault::Split(SimDuration::from_secs_f64(ms / 1000.0)),
            link,
        ),
        Fault::Exception { code, link } => {
            let (code, link) = number_or_link(code, link, "exception code")?;
            let refusal = Refusal::from_code(code.unwrap_or(4))
                .ok_or("exception code must be 1, 2, 3 or 4")?;
            (LinkFault::Exception(refusal), link)
        }
        Fault::WrongId { id, link } => {
            let (id, link) = number_or_link(id, link, "wrong-id's id")?;
            if id.is_some_and(|id| !(1..=247).contains(&id)) {
                return Err("wrong-id: the id must be 1 to 247 (MEB: 1 to 99)".into());
            }
            (LinkFault::WrongId(id), link)
        }
        Fault::Junk { bytes, place, link } => {
            let (place, link) = match (place.as_deref(), link) {
                (Some("after"), link) => (JunkPlace::After, link),
                (Some("before") | None, link) => (JunkPlace::Before, link),
                (Some(_), None) => (JunkPlace::Before, place),
                (Some(other), Some(_)) => {
                    return Err(format!(
                        "junk goes `after` or `before` the reply, not `{other}`"
                    ));
                }
            };
            (LinkFault::Junk(Junk { bytes, place }), link)
        }
        Fault::Off => return Ok(None),
    }))
}

/// `[NUMBER] [LINK]`: a first word that is no number is the link.
fn number_or_link(
    first: Option<String>,
    link: Option<String>,
    what: &str,
) -> Result<(Option<u8>, Option<String>), String> {
    match (first, link) {
        (None, link) => Ok((None, link)),
        (Some(word), link) => match word.parse::<u8>() {
            Ok(n) => Ok((Some(n), link)),
            Err(_) if link.is_none() => Ok((None, Some(word))),
            Err(_) => Err(format!("{what} `{word}` is not a number")),
        },
    }
}

fn link_index(engine: &RtEngine, name: Option<&str>) -> Result<Option<usize>, String> {
    let Some(name) = name else { return Ok(None) };
    engine
        .links
        .iter()
        .position(|l| l.name == name || l.protocol == name)
        .map(Some)
        .ok_or_else(|| {
            let names: Vec<&str> = engine.links.iter().map(|l| l.name.as_str()).collect();
            format!("no link `{name}` (links: {})", names.join(", "))
        })
}

/// Milliseconds in `range`, for the fault named `what`.
fn millis(text: &str, range: std::ops::RangeInclusive<f64>, what: &str) -> Result<f64, String> {
    let rule = format!("{what} must be {}-{} ms", range.start(), range.end());
    let ms = text
        .parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| {
            format!(
                "must be a number of milliseconds, {}-{}",
                range.start(),
                range.end()
            )
        })?;
    if range.contains(&ms) {
        Ok(ms)
    } else {
        Err(rule)
    }
}

fn delay_ms(text: &str) -> Result<f64, String> {
    millis(text, 0.0..=60_000.0, "delay")
}

fn split_ms(text: &str) -> Result<f64, String> {
    millis(text, 0.0..=10_000.0, "split gap")
}

/// `N` random bytes, or `hex:00ff7e` these bytes.
fn junk_bytes(what: &str) -> Result<JunkBytes, String> {
    let rule = format!("junk takes a count (1 to {MAX_JUNK}) or hex:BYTES (e.g. hex:00ff)");
    let bytes = match what.strip_prefix("hex:") {
        Some(hex) => protocols::hex::bytes(hex)
            .ok()
            .and_then(|b| JunkBytes::given(&b)),
        None => what.parse::<usize>().ok().and_then(JunkBytes::random),
    };
    bytes.ok_or(rule)
}

fn released(name: &str) -> Result<Released, String> {
    if name.eq_ignore_ascii_case("all") {
        return Ok(Released(None));
    }
    Input::parse(name).map(|i| Released(Some(i))).map_err(|_| {
        format!(
            "cannot release `{name}`: v1, v2, i, rpm_m, rpm_l, ldr, hall, flag, driver_fault or all"
        )
    })
}

/// `help force`'s list: every input, what it is and what it takes.
fn inputs_help() -> String {
    let mut text = String::from("Inputs:\n");
    for input in Input::ALL {
        let upper = input.name().to_ascii_uppercase();
        let takes = input.takes();
        let takes = takes
            .strip_prefix(&format!("{upper} takes "))
            .unwrap_or(&takes);
        text += &format!("  {:<13} {}: {takes}\n", input.name(), input.label());
    }
    text
}

/// Reads commands from stdin on its own thread until stdin closes; the
/// session goes on without a console (CI has no stdin).
pub fn spawn_stdin(engine: Sender<Inbound>) {
    let _ = std::thread::Builder::new()
        .name("twin-console".into())
        .spawn(move || {
            let stdin = std::io::stdin();
            let mut line = String::new();
            loop {
                line.clear();
                if !wait_for_a_line(&stdin) {
                    break;
                }
                match stdin.lock().read_line(&mut line) {
                    Ok(0) | Err(_) => break,
                    Ok(_) => {}
                }
                let message = match parse(line.trim_end_matches(['\n', '\r'])) {
                    Ok(Some(command)) => Inbound::Command(command),
                    Ok(None) => continue,
                    Err(why) => Inbound::Command(Box::new(move |e: &mut RtEngine| e.say(why))),
                };
                if engine.send(message).is_err() {
                    break;
                }
            }
        });
}

/// Whether this process is in the foreground of the terminal `stdin` is,
/// or `stdin` is no terminal (a pipe, a file, /dev/null). A process in the
/// background that reads its terminal is stopped by it (SIGTTIN: "Stopped
/// (tty input)"), and stopped it would serve nobody.
pub fn stdin_is_ours(stdin: &std::io::Stdin) -> bool {
    if !rustix::termios::isatty(stdin) {
        return true;
    }
    rustix::termios::tcgetpgrp(stdin).is_ok_and(|group| group == rustix::process::getpgrp())
}

/// Waits until a line can be read without the terminal stopping the
/// process: at once from a pipe or file; from a terminal only while in its
/// foreground, so a session started with `&` reads nothing until `fg`
/// brings it forward, and one sent back with `bg` stops reading. A
/// terminal's line is whole when poll says so (canonical mode), so the read
/// that follows does not wait. False when the terminal went away.
fn wait_for_a_line(stdin: &std::io::Stdin) -> bool {
    use rustix::event::{PollFd, PollFlags, Timespec, poll};
    if !rustix::termios::isatty(stdin) {
        return true;
    }
    let half_a_second = Timespec {
        tv_sec: 0,
        tv_nsec: 500_000_000,
    };
    loop {
        if !stdin_is_ours(stdin) {
            // Not polled: a line waiting for the shell would wake it at once.
            let _ = poll(&mut [], Some(&half_a_second));
            continue;
        }
        let mut fds = [PollFd::new(stdin, PollFlags::IN)];
        match poll(&mut fds, Some(&half_a_second)) {
            Ok(0) => continue,
            Ok(_) => {
                let got = fds[0].revents();
                if got.intersects(PollFlags::HUP | PollFlags::ERR | PollFlags::NVAL)
                    && !got.contains(PollFlags::IN)
                {
                    return false;
                }
                // Sent to the background between the two checks: wait again.
                if stdin_is_ours(stdin) {
                    return true;
                }
            }
            Err(rustix::io::Errno::INTR) => continue,
            Err(_) => return false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What `line` prints instead of running (help or a mistake), or `None`
    /// when it is a command.
    fn refused(line: &str) -> Option<String> {
        parse(line).err()
    }

    #[test]
    fn every_command_parses_in_its_old_spelling() {
        assert!(parse("").unwrap().is_none());
        assert!(parse("   ").unwrap().is_none());
        for ok in [
            "help",
            "?",
            "help fault",
            "? force",
            "status",
            "clients",
            "fault bad-check",
            "fault bad-check meb",
            "fault no-reply modbus-tcp",
            "fault delay 20 meb",
            "fault exception",
            "fault exception 2",
            "fault exception meb",
            "fault exception 3 modbus-rtu",
            "fault wrong-id",
            "fault wrong-id 7 rtu",
            "fault wrong-id meb",
            "fault split 5",
            "fault split 2.5 meb",
            "fault junk 3",
            "fault junk hex:00ff after",
            "fault junk 4 after meb",
            "fault junk 4 meb",
            "fault off",
            "force v1 30.5",
            "force I -2",
            "force hall 5",
            "force flag on",
            "force driver_fault off",
            "release flag",
            "release all",
            "read-only on",
            "read-only off",
            "stop",
            "quit",
            "exit",
        ] {
            assert!(
                parse(ok).is_ok_and(|c| c.is_some()),
                "{ok}: {:?}",
                refused(ok)
            );
        }
    }

    #[test]
    fn mistakes_say_why_in_words() {
        for (bad, why) in [
            ("fault delay soon", "must be a number"),
            ("fault delay -5", "delay must be 0-60000 ms"),
            ("fault exception 9", "1, 2, 3 or 4"),
            ("fault exception 2 meb extra", "unexpected argument 'extra'"),
            ("fault wrong-id 0", "1 to 247"),
            ("fault wrong-id x meb", "`x` is not a number"),
            ("fault split", "<MS>"),
            ("fault split 20000", "0-10000 ms"),
            ("fault junk 0", "a count (1 to 32)"),
            ("fault junk hex:0g", "hex:BYTES"),
            ("fault junk 99", "a count"),
            ("fault junk 4 sideways meb", "`after` or `before`"),
            ("fault sideways", "unrecognized subcommand 'sideways'"),
            ("force v9 1", "cannot force `v9`"),
            ("force rpm_m -3", "RPM_M takes 0 to 65535 rpm"),
            ("force v1 500", "V1 takes 0 to 100 V"),
            ("force hall 9", "0 to 7"),
            ("force flag maybe", "on or off"),
            ("release v9", "cannot release `v9`"),
            ("read-only maybe", "[possible values: on, off]"),
            ("status now", "unexpected argument 'now'"),
            ("frobnicate", "unrecognized subcommand 'frobnicate'"),
        ] {
            let e = refused(bad).unwrap_or_default();
            assert!(e.starts_with("error: "), "{bad}: {e}");
            assert!(e.contains(why), "{bad}: {e}");
            // Printed to a pipe here: no terminal's colours.
            assert!(!e.contains('\x1b'), "{bad}: {e:?}");
        }
        // An unknown command gets a hint: the one meant, and where the list is.
        let e = refused("statu").unwrap_or_default();
        assert!(e.contains("a similar subcommand exists: 'status'"), "{e}");
        assert!(e.contains("try 'help'"), "{e}");
    }

    #[test]
    fn help_lists_every_command_and_each_command_its_words() {
        let help = |line: &str| match typed_line::read::<Line>(line) {
            Ok(Typed::Help(text)) => text,
            other => panic!("{line}: {other:?}"),
        };
        let all = help("help");
        for command in [
            "status",
            "clients",
            "fault",
            "force",
            "release",
            "read-only",
            "stop",
        ] {
            assert!(all.contains(&format!("\n  {command} ")), "{command}: {all}");
        }
        let faults = help("help fault");
        for fault in [
            "bad-check",
            "no-reply",
            "delay",
            "exception",
            "wrong-id",
            "split",
            "junk",
            "off",
        ] {
            assert!(
                faults.contains(&format!("\n  {fault} ")),
                "{fault}: {faults}"
            );
        }
        assert!(
            help("help fault junk").contains("fault junk <N|hex:BYTES> [after|before] [LINK]"),
            "{}",
            help("help fault junk")
        );
        let inputs = help("help force");
        for input in Input::ALL {
            assert!(inputs.contains(input.name()), "{input:?}: {inputs}");
        }
        assert!(inputs.contains("0 to 100 V"), "{inputs}");
        // `fault` alone is a question: its list, not a mistake.
        assert_eq!(help("fault"), faults);
    }
}
