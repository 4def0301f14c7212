//! The page, embedded at compile time: no bundler, nothing fetched, so the
//! panel works in a lab without a network.

pub const INDEX_HTML: &str = include_str!("../assets/index.html");
pub const PANEL_CSS: &str = include_str!("../assets/panel.css");
pub const PANEL_JS: &str = include_str!("../assets/panel.js");
