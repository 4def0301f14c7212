//! `twin scope RUN.mcap --vcd OUT` without the rest of `twin`, so its speed
//! is measured in a release build that does not link rerun:
//! `cargo build --release -p twin-scope --example vcd`, then
//! `farm-bench -- target/release/examples/vcd RUN.mcap OUT.vcd`.

use std::fs::File;
use std::io::BufWriter;
use std::path::PathBuf;
use std::process::ExitCode;

use twin_scope::{Choice, Window};

fn main() -> ExitCode {
    let args: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    let [recording, out] = args.as_slice() else {
        eprintln!("usage: vcd RUN.mcap OUT.vcd");
        return ExitCode::from(2);
    };
    let choice = Choice {
        bus: None,
        window: Window::All,
        baud: None,
    };
    let written = twin_scope::load(recording, &choice).and_then(|wave| {
        let file = File::create(out).map_err(|source| twin_scope::ScopeError::Write {
            path: out.clone(),
            source,
        })?;
        twin_scope::vcd_out::write(&wave, BufWriter::new(file)).map_err(|source| {
            twin_scope::ScopeError::Write {
                path: out.clone(),
                source,
            }
        })
    });
    match written {
        Ok(w) => {
            println!("{} lines, {} edges", w.lines, w.edges);
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
