//! `twin client`: the remote MEB client over TCP.

use anyhow::{Result, bail};
use clap::{Args, Subcommand};
use protocols::meb::MebCmd;
use std::io::{BufRead, Write};
use std::time::{Duration, Instant};
use twin_realtime::client::{
    ClientError, MebClient, Prompt, Way, parse_addr, parse_cmd, parse_word, tag,
};
use twin_realtime::typed_line::{self, Typed};

/// Talk MEB over TCP to a supervisor (`twin supervise --listen`) or an MEB slave.
///
/// One-shot commands for scripts print the words and exit 0, or print what
/// went wrong and exit 1 (an ER reply, no reply within --timeout-ms, a closed
/// connection). ADDR is hex as on the wire (FA 10 is 0x10); values are
/// decimal, or hex with 0x. Without a command: an interactive prompt.
#[derive(Debug, Args)]
#[command(
    after_help = "Examples:\n  twin client tcp://127.0.0.1:5701 read EA 0 3\n  twin client tcp://127.0.0.1:5701 write SA 0 2048\n  twin client tcp://127.0.0.1:5701 write VA 10 1500     (the loop's set point, rpm)\n  twin client tcp://127.0.0.1:5701 watch --count 5\n  twin client tcp://127.0.0.1:5701                      (interactive)"
)]
pub struct ClientArgs {
    /// Where the server listens: tcp://HOST:PORT.
    url: String,
    #[command(subcommand)]
    command: Option<ClientCommand>,
    /// Slave id to address.
    #[arg(long, default_value_t = 1, global = true,
          value_parser = clap::value_parser!(u8).range(0..=99))]
    id: u8,
    /// How long to wait for the connection and for each reply, ms.
    #[arg(long, default_value_t = 1000, global = true, value_name = "MS", value_parser = super::numbers::whole::<u64>)]
    timeout_ms: u64,
    /// Show every frame both ways (on stderr).
    #[arg(short, long, global = true)]
    verbose: bool,
}

#[derive(Debug, Subcommand)]
enum ClientCommand {
    /// Read CNT words from CMD ADDR, e.g. `read EA 0 3`.
    Read {
        cmd: String,
        addr: String,
        #[arg(default_value_t = 1, value_parser = super::numbers::whole::<u8>)]
        cnt: u8,
    },
    /// Write words to CMD ADDR, e.g. `write SA 0 2048` or `write SD 0 0x000E 0x0001`.
    Write {
        cmd: String,
        addr: String,
        #[arg(required = true)]
        values: Vec<String>,
    },
    /// Print the inputs (EA 00-05) and the loop (FA 10-12, FD 10) periodically.
    Watch {
        /// Seconds between readings.
        #[arg(long, default_value_t = 0.5, value_parser = super::numbers::above_zero)]
        every: f64,
        /// Stop after this many readings [default: until Ctrl-C].
        #[arg(long, value_parser = super::numbers::whole::<u64>)]
        count: Option<u64>,
    },
}

pub fn execute(args: &ClientArgs) -> Result<()> {
    let mut client = MebClient::connect(&args.url, Duration::from_millis(args.timeout_ms.max(1)))?;
    if args.verbose {
        client.set_monitor(|way, at, bytes| {
            let arrow = match way {
                Way::Sent => "->",
                Way::Received => "<-",
            };
            eprintln!(
                "[{at:10.6} s] {arrow} {}",
                String::from_utf8_lossy(bytes).trim_end()
            );
        });
    }
    let id = args.id;
    match &args.command {
        Some(ClientCommand::Read { cmd, addr, cnt }) => {
            let cmd = parse_cmd(cmd)?;
            let addr = parse_addr(addr)?;
            let words = client.read(id, cmd, addr, *cnt)?;
            print_words(cmd, addr, &words);
        }
        Some(ClientCommand::Write { cmd, addr, values }) => {
            let cmd = parse_cmd(cmd)?;
            let addr = parse_addr(addr)?;
            let words = values
                .iter()
                .map(|v| parse_word(v))
                .collect::<Result<Vec<_>, _>>()?;
            client.write(id, cmd, addr, &words)?;
            if id == 0 {
                println!(
                    "{cmd} {addr:02X}: {} word(s) broadcast (never acknowledged)",
                    words.len()
                );
            } else {
                println!("{cmd} {addr:02X}: {} word(s) acknowledged", words.len());
            }
        }
        Some(ClientCommand::Watch { every, count }) => {
            if !(every.is_finite() && *every > 0.0) {
                bail!("--every must be a positive number of seconds");
            }
            watch(&mut client, id, Duration::from_secs_f64(*every), *count)?;
        }
        None => interactive(&mut client, id)?,
    }
    Ok(())
}

fn print_words(cmd: MebCmd, addr: u8, words: &[u16]) {
    for (i, word) in words.iter().enumerate() {
        let a = usize::from(addr) + i;
        let name = tag(cmd, a).map_or(String::new(), |t| format!("  {t}"));
        println!("{cmd} {a:02X} = {word:5}  (0x{word:04X}){name}");
    }
}

/// One line: the six inputs, and the loop if the server holds one.
fn reading(client: &mut MebClient, id: u8) -> Result<String, ClientError> {
    let inputs = client.read(id, MebCmd::EA, 0, 6)?;
    let mut line = ["V2", "I", "V1", "RPM_M", "RPM_L", "LDR"]
        .iter()
        .zip(&inputs)
        .map(|(name, w)| format!("{name} {w}"))
        .collect::<Vec<_>>()
        .join("  ");
    // An MEB slave served directly has no loop: its FA 10 is not there.
    if let (Ok(mirrors), Ok(closed)) = (
        client.read(id, MebCmd::FA, 0x10, 3),
        client.read(id, MebCmd::FD, 0x10, 1),
    ) {
        let state = if closed.first() == Some(&1) {
            "closed"
        } else {
            "open"
        };
        line += &format!(
            "  | loop {state}, set point {} rpm, kp {:.3}, ki {:.3}",
            mirrors[0],
            f64::from(mirrors[1]) / 1000.0,
            f64::from(mirrors[2]) / 1000.0
        );
    }
    Ok(line)
}

fn watch(client: &mut MebClient, id: u8, every: Duration, count: Option<u64>) -> Result<()> {
    let start = Instant::now();
    let mut n = 0u64;
    loop {
        let line = reading(client, id)?;
        println!("[{:8.3} s] {line}", start.elapsed().as_secs_f64());
        n += 1;
        if count.is_some_and(|c| n >= c) {
            return Ok(());
        }
        let next = start + every.mul_f64(n as f64);
        std::thread::sleep(next.saturating_duration_since(Instant::now()));
    }
}

fn interactive(client: &mut MebClient, id: u8) -> Result<()> {
    println!("twin client: connected, slave {id:02}; `help` lists the commands");
    match reading(client, id) {
        Ok(line) => println!("{line}"),
        Err(e) => println!("error: {:#}", anyhow::Error::from(e)),
    }
    let stdin = std::io::stdin();
    loop {
        print!("meb> ");
        std::io::stdout().flush()?;
        let mut line = String::new();
        if stdin.lock().read_line(&mut line)? == 0 {
            return Ok(());
        }
        let prompt = match typed_line::read::<Prompt>(&line) {
            Ok(Typed::Command(prompt)) => prompt,
            Ok(Typed::Blank) => continue,
            Ok(Typed::Help(text)) | Err(text) => {
                println!("{text}");
                continue;
            }
        };
        // Ok(true): a write went through; the inputs are shown after it.
        let result: Result<bool, ClientError> = match prompt {
            Prompt::Quit => return Ok(()),
            Prompt::Show => reading(client, id).map(|l| {
                println!("{l}");
                false
            }),
            Prompt::Read { cmd, addr, cnt } => client.read(id, cmd, addr, cnt).map(|words| {
                print_words(cmd, addr, &words);
                false
            }),
            Prompt::Write { cmd, addr, values } => client.write(id, cmd, addr, &values).map(|()| {
                println!("acknowledged");
                true
            }),
            Prompt::SetPoint { rpm } => client.write(id, MebCmd::VA, 0x10, &[rpm]).map(|()| true),
            Prompt::Gains { kp, ki } => {
                client.write(id, MebCmd::VA, 0x11, &[kp, ki]).map(|()| true)
            }
            Prompt::Loop { on } => client
                .write(id, MebCmd::VD, 0x10, &[u16::from(on.is_on())])
                .map(|()| true),
            Prompt::Vel { counts } => client.write(id, MebCmd::SA, 0, &[counts]).map(|()| true),
            Prompt::Enable => client.write(id, MebCmd::SD, 0, &[0x000E]).map(|()| true),
            Prompt::Disable => client.write(id, MebCmd::SD, 0, &[0x001F]).map(|()| true),
        };
        match result {
            Ok(true) => {
                if let Ok(l) = reading(client, id) {
                    println!("{l}");
                }
            }
            Ok(false) => {}
            // Through anyhow, so the causes are said too, as `main` says them.
            Err(e) => println!("error: {:#}", anyhow::Error::from(e)),
        }
    }
}
