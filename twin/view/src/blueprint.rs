//! The layout a student sees: per module, the speeds on one plot, V1/V2, I
//! and SOC beside each other, the photoresistor signal with its dips; the
//! bus frames and the events as text logs on the right; for a real-time
//! session, the tick lateness under the plots.

use rerun::blueprint::components::PanelState;
use rerun::blueprint::{
    Blueprint, BlueprintPanel, ContainerLike, Horizontal, SelectionPanel, Tabs, TextLogView,
    TimePanel, TimeSeriesView, Vertical,
};

use super::layout::ViewLayout;
use super::logger::{EVENTS, LATENESS, TIMELINE};

fn plot(name: &str, contents: &str) -> ContainerLike {
    TimeSeriesView::new(name)
        .with_origin("/")
        .with_contents([contents.to_string()])
        .into()
}

/// One module's plots, top to bottom.
fn module_column(layout: &ViewLayout, m: usize) -> Vertical {
    let name = &layout.modules[m].name;
    let mut rows = vec![plot(
        &format!("{name}: speed (rpm)"),
        &format!("/{name}/speed/**"),
    )];
    let mut shares = vec![3.0];
    if !layout.modules[m].has_plant {
        // A supervisor's session: only what the slave's replies carry.
        return Vertical::new(rows)
            .with_name(name.clone())
            .with_row_shares(shares);
    }
    if layout.has_controller_network(m) {
        rows.push(plot(
            &format!("{name}: motor shaft (rpm)"),
            &format!("/{name}/motor_shaft/**"),
        ));
        shares.push(2.0);
    }
    rows.push(
        Horizontal::new([
            plot(
                &format!("{name}: V1, V2 (V)"),
                &format!("/{name}/voltage/**"),
            ),
            plot(&format!("{name}: I (A)"), &format!("/{name}/current/**")),
            plot(&format!("{name}: SOC (%)"), &format!("/{name}/soc/**")),
        ])
        .into(),
    );
    shares.push(2.0);
    rows.push(plot(
        &format!("{name}: photoresistor (V) and detected dips"),
        &format!("/{name}/photoresistor/**"),
    ));
    shares.push(2.0);
    rows.push(plot(
        &format!("{name}: flag in beam / detector dark"),
        &format!("/{name}/flag/**"),
    ));
    shares.push(1.0);
    // Compiled firmware beside the plant: its pins' duty and levels and
    // the ADC counts fed to it (its UART is with the frames).
    for (node, _) in layout.firmware.iter().filter(|(_, fm)| *fm == m) {
        rows.push(
            Horizontal::new([
                plot(
                    &format!("{node} firmware: pins (duty, level)"),
                    &format!("/{node}/firmware/pins/**"),
                ),
                plot(
                    &format!("{node} firmware: ADC inputs (counts)"),
                    &format!("/{node}/firmware/adc/**"),
                ),
            ])
            .into(),
        );
        shares.push(2.0);
    }
    Vertical::new(rows)
        .with_name(name.clone())
        .with_row_shares(shares)
}

/// The whole layout for `layout`'s modules.
pub fn blueprint(layout: &ViewLayout) -> Blueprint {
    let columns: Vec<ContainerLike> = (0..layout.modules.len())
        .map(|m| module_column(layout, m).into())
        .collect();
    let plots: ContainerLike = match columns.len() {
        1 => columns.into_iter().next().expect("one column"),
        _ => Tabs::new(columns).into(),
    };
    // A real-time session: how late the plant's ticks ran, below the bench.
    let plots: ContainerLike = if layout.realtime {
        Vertical::new([
            plots,
            plot(
                "tick lateness (µs), each second",
                &format!("/{LATENESS}/**"),
            ),
        ])
        .with_row_shares([6.0, 1.0])
        .into()
    } else {
        plots
    };
    let mut logs: Vec<ContainerLike> = vec![
        TextLogView::new("bus frames")
            .with_origin("/bus")
            .with_contents(["$origin/**"])
            .into(),
    ];
    let mut log_shares = vec![3.0];
    for (node, _) in &layout.firmware {
        logs.push(
            TextLogView::new(format!("{node} firmware UART"))
                .with_origin(format!("/{node}/firmware/uart"))
                .with_contents(["$origin"])
                .into(),
        );
        log_shares.push(2.0);
    }
    logs.push(
        TextLogView::new("events")
            .with_origin(format!("/{EVENTS}"))
            .with_contents(["$origin"])
            .into(),
    );
    log_shares.push(1.0);
    let logs = Vertical::new(logs).with_row_shares(log_shares);
    Blueprint::new(Horizontal::new([plots, logs.into()]).with_column_shares([3.0, 2.0]))
        .with_blueprint_panel(BlueprintPanel::new().with_state(PanelState::Collapsed))
        .with_selection_panel(SelectionPanel::new().with_state(PanelState::Collapsed))
        // Collapsed to its play bar: the plots get the room.
        .with_time_panel(
            TimePanel::new()
                .with_timeline(TIMELINE)
                .with_state(PanelState::Collapsed),
        )
}
