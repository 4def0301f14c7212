//! Commands typed while `twin serve` runs (one per line on stdin): faults,
//! forced inputs, read-only, status. Parsed here, run on the engine's thread.

use nodes::firmware::Refusal;
use nodes::link::{Junk, JunkBytes, JunkPlace, MAX_JUNK};
use protocols::time::SimDuration;
use std::io::BufRead;
use std::sync::mpsc::Sender;

use crate::{Inbound, LinkFault, RtEngine};

/// The help text of the console.
pub const HELP: &str = "\
commands:
  status                       the module's state, clients, tick lateness
  clients                      open connections
  fault bad-check [LINK]       replies go out with their check value + 1 (MEB, RTU, modbus8)
  fault no-reply [LINK]        requests are served but never answered
  fault delay MS [LINK]        replies go out MS milliseconds late
  fault exception [CODE] [LINK]  every request refused: Modbus exception / MEB ER CODE (1-4, default 4;
                               MEB and Modbus links, not --modbus8)
  fault wrong-id [ID] [LINK]   replies come from slave ID (default: the next id), check good
                               (MEB, RTU, modbus8)
  fault split MS [LINK]        each reply in two writes, the second MS milliseconds after the first
  fault junk N|hex:BYTES [after] [LINK]  N random bytes (or these, e.g. hex:00ff) before each
                               reply (after it with `after`)
  fault off                    no fault
  force v1|v2 VOLTS            the controller measures this battery / bus voltage
  force i AMPS                 ... this inverter current
  force rpm_m|rpm_l|ldr COUNTS the input word reads this
  force hall CODE              the hall sensors read this code (0-7: bit 0 A, 1 B, 2 C)
  force flag on|off            the photoresistor sees the flag (dark) or not
  force driver_fault on|off    the motor driver reports a fault (the inverter trips)
  release NAME|all             measure NAME again
  read-only on|off             refuse writes from every client
  stop                         end the session (as SIGINT)
  help                         this text";

/// A parsed console command: what to run on the engine.
pub type Command = Box<dyn FnOnce(&mut RtEngine) + Send>;

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

/// Parses one line; `Err` is the message to print.
pub fn parse(line: &str) -> Result<Option<Command>, String> {
    let words: Vec<&str> = line.split_whitespace().collect();
    let number = |w: Option<&&str>, what: &str| -> Result<f64, String> {
        w.ok_or_else(|| format!("missing {what}"))?
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| format!("{what} must be a number"))
    };
    let command: Command = match words.as_slice() {
        [] => return Ok(None),
        ["help" | "?"] => Box::new(|e: &mut RtEngine| e.say(HELP)),
        ["status"] => Box::new(|e: &mut RtEngine| {
            let line = e.status_line(e.clock.now());
            e.say(line);
        }),
        ["clients"] => Box::new(|e: &mut RtEngine| {
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
        ["stop" | "quit" | "exit"] => Box::new(|e: &mut RtEngine| {
            e.say("stopping");
            e.request_stop("console");
        }),
        ["read-only", on] => {
            let on = match *on {
                "on" => true,
                "off" => false,
                _ => return Err("read-only on|off".into()),
            };
            Box::new(move |e: &mut RtEngine| {
                e.set_read_only(on);
                e.say(format!("read-only {}", if on { "on" } else { "off" }));
            })
        }
        ["fault", "off"] => Box::new(|e: &mut RtEngine| {
            e.set_fault(None, None);
            e.say("fault off");
        }),
        ["fault", kind, rest @ ..] => {
            let (fault, link) = match (*kind, rest) {
                ("bad-check", link) => (LinkFault::BadCheck, link.first().copied()),
                ("no-reply", link) => (LinkFault::NoReply, link.first().copied()),
                ("delay", [ms, link @ ..]) => {
                    let ms = number(Some(ms), "delay (ms)")?;
                    if !(0.0..=60_000.0).contains(&ms) {
                        return Err("delay must be 0-60000 ms".into());
                    }
                    let d = SimDuration::from_secs_f64(ms / 1000.0);
                    (LinkFault::Delay(d), link.first().copied())
                }
                ("exception", args) => {
                    let (code, link) = match args {
                        [] => (4, None),
                        [c, link @ ..] if c.parse::<u8>().is_ok() => {
                            (c.parse::<u8>().unwrap_or(4), link.first().copied())
                        }
                        [link, ..] => (4, Some(*link)),
                    };
                    let Some(refusal) = Refusal::from_code(code) else {
                        return Err("exception code must be 1, 2, 3 or 4".into());
                    };
                    (LinkFault::Exception(refusal), link)
                }
                ("wrong-id", args) => match args {
                    [id, link @ ..] if id.parse::<u8>().is_ok() => {
                        let id = id.parse::<u8>().ok().filter(|&id| (1..=247).contains(&id));
                        let Some(id) = id else {
                            return Err("wrong-id: the id must be 1 to 247 (MEB: 1 to 99)".into());
                        };
                        (LinkFault::WrongId(Some(id)), link.first().copied())
                    }
                    link => (LinkFault::WrongId(None), link.first().copied()),
                },
                ("split", [ms, link @ ..]) => {
                    let ms = number(Some(ms), "split gap (ms)")?;
                    if !(0.0..=10_000.0).contains(&ms) {
                        return Err("split gap must be 0-10000 ms".into());
                    }
                    let gap = SimDuration::from_secs_f64(ms / 1000.0);
                    (LinkFault::Split(gap), link.first().copied())
                }
                ("junk", [what, rest @ ..]) => {
                    let (place, link) = match rest {
                        ["after", link @ ..] => (JunkPlace::After, link.first().copied()),
                        ["before", link @ ..] => (JunkPlace::Before, link.first().copied()),
                        [link, ..] => (JunkPlace::Before, Some(*link)),
                        [] => (JunkPlace::Before, None),
                    };
                    let bytes = junk_bytes(what)?;
                    (LinkFault::Junk(Junk { bytes, place }), link)
                }
                _ => return Err(format!("unknown fault `{kind}`; try `help`")),
            };
            let link = link.map(str::to_string);
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
        ["force", name, value] => {
            let forced = crate::forces::Input::parse(name)
                .and_then(|input| input.value_text(value))
                .map_err(|e| e.to_string())?;
            let name = forced.input().name();
            Box::new(move |e: &mut RtEngine| {
                e.force(forced);
                e.say(format!("forced {name} = {forced}"));
            })
        }
        ["release", name] => {
            let input = match name.to_ascii_lowercase().as_str() {
                "all" => None,
                _ => Some(crate::forces::Input::parse(name).map_err(|_| {
                    format!(
                        "cannot release `{name}`: v1, v2, i, rpm_m, rpm_l, ldr, hall, flag, driver_fault or all"
                    )
                })?),
            };
            Box::new(move |e: &mut RtEngine| {
                for d in &mut e.devices {
                    match input {
                        Some(input) => d.forces.release(input),
                        None => d.forces = Default::default(),
                    }
                }
                e.say(format!("released {}", input.map_or("all", |i| i.name())));
            })
        }
        _ => return Err(format!("unknown command `{}`; try `help`", line.trim())),
    };
    Ok(Some(command))
}

/// `N` random bytes, or `hex:00ff7e` these bytes.
fn junk_bytes(what: &str) -> Result<JunkBytes, String> {
    let rule = format!("junk takes a count (1 to {MAX_JUNK}) or hex:BYTES (e.g. hex:00ff)");
    if let Some(hex) = what.strip_prefix("hex:") {
        let bytes: Option<Vec<u8>> = (hex.len() % 2 == 0)
            .then(|| {
                (0..hex.len())
                    .step_by(2)
                    .map(|i| {
                        hex.get(i..i + 2)
                            .and_then(|b| u8::from_str_radix(b, 16).ok())
                    })
                    .collect()
            })
            .flatten();
        return bytes.and_then(|b| JunkBytes::given(&b)).ok_or(rule);
    }
    what.parse::<usize>()
        .ok()
        .and_then(JunkBytes::random)
        .ok_or(rule)
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

    #[test]
    fn commands_parse_and_mistakes_say_why() {
        assert!(parse("").unwrap().is_none());
        for ok in [
            "help",
            "status",
            "fault bad-check",
            "fault delay 20 meb",
            "fault exception 2",
            "fault wrong-id",
            "fault wrong-id 7 rtu",
            "fault split 5",
            "fault split 2.5 meb",
            "fault junk 3",
            "fault junk hex:00ff after",
            "fault junk 4 after meb",
            "fault off",
            "force v1 30.5",
            "force hall 5",
            "force flag on",
            "force driver_fault off",
            "release flag",
            "release all",
            "read-only on",
        ] {
            assert!(parse(ok).unwrap().is_some(), "{ok}");
        }
        for (bad, why) in [
            ("fault delay soon", "must be a number"),
            ("fault exception 9", "1, 2, 3 or 4"),
            ("fault wrong-id 0", "1 to 247"),
            ("fault split", "unknown fault"),
            ("fault split 20000", "0-10000 ms"),
            ("fault junk 0", "a count (1 to 32)"),
            ("fault junk hex:0g", "hex:BYTES"),
            ("fault junk 99", "a count"),
            ("force v9 1", "cannot force `v9`"),
            ("force rpm_m -3", "RPM_M takes 0 to 65535 rpm"),
            ("force v1 500", "V1 takes 0 to 100 V"),
            ("force hall 9", "0 to 7"),
            ("force flag maybe", "on or off"),
            ("release v9", "cannot release `v9`"),
            ("frobnicate", "unknown command"),
        ] {
            let e = parse(bad).err().unwrap_or_default();
            assert!(e.contains(why), "{bad}: {e}");
        }
    }
}
