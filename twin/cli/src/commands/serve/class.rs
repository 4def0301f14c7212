//! A class from one `twin serve`: a configuration file's `[[module]]`
//! tables, each an independent simulated module (its own plant, links,
//! allowed addresses and recordings, in a folder of its name) served side
//! by side in one process. Each module is the session `twin serve` would
//! run for it alone, on threads of its own; the process prints every
//! module's links, then `ready` once all are open, and stops them all on
//! SIGTERM, each finishing its recording. An `[index]` table serves the
//! class's index, the teacher's page of every module, behind a token of its
//! own.

use anyhow::{Context, Result, anyhow, bail};
use clap::{ArgMatches, Command};
use std::io::Write;
use std::sync::mpsc::{Sender, channel};
use twin_realtime::Inbound;
use twin_realtime::serve::{self, OpenLink, ServeOptions};

use super::super::config_file::ConfigFile;
use super::super::service::{Reread, reparse};
use super::ServeArgs;

/// What a module's thread reports to the class.
enum Report {
    Ready(usize, Vec<OpenLink>),
    Console(usize, Sender<Inbound>),
    Done(usize, Box<Result<twin_realtime::session::SessionOutcome>>),
}

/// Options given on the command line that would make every module the same.
const PER_MODULE: &[&str] = &[
    "meb",
    "modbus",
    "modbus_rtu",
    "modbus_ascii",
    "modbus8",
    "out",
];

pub fn execute(
    file: &ConfigFile,
    command: &Command,
    given: &ArgMatches,
    check: bool,
) -> Result<()> {
    for id in PER_MODULE {
        if given.value_source(id) == Some(clap::parser::ValueSource::CommandLine) {
            bail!(
                "--{}: the class in {} gives each module its own; set it in the module's [[module]] table",
                id.replace('_', "-"),
                file.origin
            );
        }
    }
    let mut modules = Vec::new();
    for m in &file.modules {
        let args: ServeArgs = reparse(command, file.words(Some(m), given))
            .map_err(|e| anyhow!("{}:{}: module {}: {e:#}", file.origin, m.line, m.name))?;
        let options = super::options(&args, Some(&m.name))
            .map_err(|e| anyhow!("{}:{}: module {}: {e:#}", file.origin, m.line, m.name))?;
        let links = if check {
            serve::check_links(&options)
        } else {
            serve::parse_links(&options).map(drop)
        };
        // Context, not the message: the link's error keeps its causes.
        links.with_context(|| format!("{}:{}: module {}", file.origin, m.line, m.name))?;
        modules.push((m.name.clone(), args, options));
    }
    if let Some(index) = &file.index {
        // The teacher's token must not be a student's: a file shared with a
        // module would open the index to that student.
        for (name, args, _) in &modules {
            if args.web.token_file(name).as_deref() == Some(index.token_file.as_path()) {
                bail!(
                    "{}:{}: `index`: its token file {} is also module {name}'s; give the index a `web-token-file` of its own",
                    file.origin,
                    index.line,
                    index.token_file.display()
                );
            }
        }
    }
    if check {
        println!("{}: a class of {} modules", file.origin, modules.len());
        for (name, args, options) in &modules {
            let panel = args.web.described(name);
            println!(
                "  {name}: {}{}",
                super::described(options),
                panel.map(|p| format!("; {p}")).unwrap_or_default()
            );
        }
        if let Some(index) = &file.index {
            println!(
                "  index: the class's page on {} (the teacher's token in {})",
                index.web,
                index.token_file.display()
            );
        }
        return Ok(());
    }
    if let Some(path) = given.get_one::<std::path::PathBuf>("config") {
        for (name, _, options) in &mut modules {
            options.session.on_hangup = Some(
                Reread::<ServeArgs> {
                    path: path.clone(),
                    command: command.clone(),
                    command_line: given.clone(),
                    module: Some(name.clone()),
                    started: file.clone(),
                    allow: options.session.allow.clone(),
                    allow_of: |a| a.service.allow.clone(),
                    plan_of: {
                        let name = name.clone();
                        Box::new(move |a| super::plan(a, Some(&name)))
                    },
                }
                .hook(),
            );
        }
    }
    // Each module's own panel, with its own token (`web-token-file` in its
    // table), bound only once the whole class has been checked.
    let mut panels = Vec::with_capacity(modules.len());
    for (name, args, options) in &mut modules {
        let panel = args
            .web
            .bind(twin_panel::PanelRole::Serve, &mut options.session, name)
            .map_err(|e| anyhow!("module {name}: {e:#}"))?
            .map(|p| p.named(name));
        let panel = match (panel, &options.meb_map) {
            (Some(p), Some(map)) => Some(p.with_map(map)),
            (panel, _) => panel,
        };
        // A module without a panel still feeds the index what it shows.
        let panel = match (panel, &file.index) {
            (None, Some(_)) => {
                let feed = twin_panel::Panel::unserved(twin_panel::PanelRole::Serve).named(name);
                super::super::web_args::feed(&feed, &mut options.session);
                Some(feed)
            }
            (panel, _) => panel,
        };
        panels.push(panel);
    }
    let index = match &file.index {
        Some(index) => {
            let bound = twin_panel::ClassIndex::bind(index.web, &index.token_file)?;
            let running = bound.running();
            bound.start(
                modules
                    .iter()
                    .zip(&panels)
                    .filter_map(|((name, _, options), panel)| {
                        Some(twin_panel::ClassModule {
                            name: name.clone(),
                            panel: panel.clone()?,
                            record: options.session.record.clone(),
                        })
                    })
                    .collect(),
            )?;
            Some(super::super::web_args::url_shown(
                &running,
                Some(&index.token_file),
            ))
        }
        None => None,
    };
    run(&modules, &panels, index.as_deref())
}

fn run(
    modules: &[(String, ServeArgs, ServeOptions)],
    panels: &[Option<twin_panel::Panel>],
    index: Option<&str>,
) -> Result<()> {
    let (tx, rx) = channel::<Report>();
    let mut stoppers: Vec<Option<Sender<Inbound>>> = vec![None; modules.len()];
    std::thread::scope(|scope| {
        for (n, (name, _, options)) in modules.iter().enumerate() {
            let (ready, console, done) = (tx.clone(), tx.clone(), tx.clone());
            let spawned = std::thread::Builder::new()
                .name(format!("twin-{name}"))
                .spawn_scoped(scope, move || {
                    let outcome = serve::serve(
                        options,
                        |links| {
                            let _ = ready.send(Report::Ready(n, links.to_vec()));
                        },
                        |engine| {
                            if let Some(panel) = &panels[n]
                                && let Err(e) = panel.start(engine.clone())
                            {
                                // With its cause, as main prints an error.
                                let e = anyhow::Error::from(e);
                                eprintln!(
                                    "module {name}: --web: {e:#}; going on without its panel"
                                );
                            }
                            let _ = console.send(Report::Console(n, engine));
                        },
                    );
                    let _ = done.send(Report::Done(n, Box::new(outcome.map_err(Into::into))));
                });
            if let Err(e) = spawned {
                let _ = tx.send(Report::Done(
                    n,
                    Box::new(Err(anyhow!("no thread for it: {e}"))),
                ));
            }
        }
        drop(tx);
        // The modules' lines wait for the last to open, then come in the
        // file's order: the order their threads opened links in is chance.
        let mut opened: Vec<Option<Vec<OpenLink>>> = vec![None; modules.len()];
        let mut failed = None;
        let mut outcomes: Vec<Option<twin_realtime::session::SessionOutcome>> =
            (0..modules.len()).map(|_| None).collect();
        while let Ok(report) = rx.recv() {
            match report {
                Report::Ready(n, links) => {
                    opened[n] = Some(links);
                    if opened.iter().any(Option::is_none) {
                        continue;
                    }
                    let mut out = std::io::stdout().lock();
                    for (n, links) in opened.iter().enumerate() {
                        let (name, args, _) = &modules[n];
                        for l in links.iter().flatten() {
                            let _ =
                                writeln!(out, "  {} {} {} {name}", l.protocol, l.address, l.ids);
                        }
                        if let Some(panel) = panels[n].as_ref().filter(|p| p.served()) {
                            let file = args.web.token_file(name);
                            let line = super::super::web_args::panel_line(panel, file.as_deref());
                            let _ = writeln!(out, "  {line} {name}");
                        }
                    }
                    if let Some(url) = index {
                        let _ = writeln!(out, "  index: {url} class");
                    }
                    let _ = writeln!(out, "twin serve: a class of {} modules", modules.len());
                    // Said once for the class, not once per module.
                    if modules
                        .iter()
                        .any(|(_, args, _)| args.rt_priority.is_none())
                    {
                        let _ = writeln!(out, "{}", super::without_priority());
                    }
                    let _ = writeln!(out, "ready");
                    let _ = out.flush();
                    twin_realtime::notify::ready(&format!(
                        "serving a class of {} modules",
                        modules.len()
                    ));
                }
                Report::Console(n, engine) => stoppers[n] = Some(engine),
                Report::Done(n, outcome) => match *outcome {
                    Ok(o) => outcomes[n] = Some(o),
                    Err(e) => {
                        // One module that cannot serve stops the class: a
                        // service manager then says so and restarts it whole.
                        let e = anyhow!("module {}: {e:#}", modules[n].0);
                        eprintln!("error: {e:#}; stopping the class");
                        for engine in stoppers.iter().flatten() {
                            let _ = engine
                                .send(Inbound::Stop(format!("module {} failed", modules[n].0)));
                        }
                        failed.get_or_insert(e);
                    }
                },
            }
        }
        for (n, outcome) in outcomes.iter().enumerate() {
            let Some(o) = outcome else { continue };
            let l = &o.lateness;
            println!(
                "{}: stopped ({}) after {:.3} s; tick lateness p99 {:.0} µs, max {:.0} µs; {} connections, {} refused (--allow), {} over the limit; recording: {}",
                modules[n].0,
                o.stopped_by,
                o.elapsed_s,
                l.p99_us,
                l.max_us,
                o.counters.connections,
                o.refused_not_allowed,
                o.refused_clients,
                o.recording
                    .as_ref()
                    .map_or_else(|| "none".into(), |p| p.display().to_string())
            );
            if let Some(line) = l.slip_line() {
                println!("{}: {line}", modules[n].0);
            }
        }
        match failed {
            Some(e) => Err(e),
            None => Ok(()),
        }
    })
}
