//! Error reporting of the `cvfarm` binary.
//!
//! Contract (operators grep logs, scripts test exit codes):
//! - a failed command prints **exactly one line** `error: <what>: <cause>: …` on stderr and
//!   exits with status 1 ([`report`]);
//! - a bad command line (unknown flag, malformed value, unknown estimator) prints one line
//!   `error: …` on stderr and exits with status 2 ([`report_clap`]; bad estimator options
//!   found after parsing are reported by [`report`] with status 2 too); `--help` and `--version`
//!   print normally and exit 0;
//! - `cvfarm compare --max-rel-mse X` exits with status 3 when the image is worse than `X`
//!   (see [`crate::compare_cmd`]).

use std::process::ExitCode;

/// Exit status of a failed command.
pub const EXIT_FAILURE: u8 = 1;
/// Exit status of a bad command line (clap's convention).
pub const EXIT_USAGE: u8 = 2;

/// Joins the error's cause chain into one line.
pub fn one_line(e: &anyhow::Error) -> String {
    // The chain, outermost first; a cause already spelled out by an outer message (thiserror's
    // `"{path}: {source}"` style) is not repeated.
    let mut text = String::new();
    for cause in e.chain() {
        let part = cause.to_string();
        if text.contains(&part) {
            continue;
        }
        if !text.is_empty() {
            text.push_str(": ");
        }
        text.push_str(&part);
    }
    squash(&text)
}

/// Collapses whitespace runs (including newlines) into single spaces.
fn squash(text: &str) -> String {
    text.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// Prints `error: …` (one line) and returns the failure exit status.
pub fn report(e: &anyhow::Error) -> ExitCode {
    eprintln!("error: {}", one_line(e));
    // A bad command line found after parsing (estimator options) is a usage error too.
    if e.chain().any(|c| {
        c.downcast_ref::<crate::estimator_opts::UsageError>()
            .is_some()
    }) {
        return ExitCode::from(EXIT_USAGE);
    }
    ExitCode::from(EXIT_FAILURE)
}

/// Reports a command-line parse error on one line (help and version are printed as is).
pub fn report_clap(e: &clap::Error) -> ExitCode {
    use clap::error::ErrorKind;
    match e.kind() {
        ErrorKind::DisplayHelp
        | ErrorKind::DisplayVersion
        | ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => {
            // Help text goes to stdout (or stderr for the missing-subcommand case) unchanged.
            let _ = e.print();
            if e.kind() == ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand {
                ExitCode::from(EXIT_USAGE)
            } else {
                ExitCode::SUCCESS
            }
        }
        _ => {
            let rendered = e.render().to_string();
            let lines: Vec<&str> = rendered
                .lines()
                .map(str::trim)
                .filter(|l| {
                    !l.is_empty()
                        && !l.starts_with("For more information")
                        && !l.starts_with("Usage:")
                })
                .collect();
            let msg = squash(&lines.join(" "));
            let msg = msg.strip_prefix("error: ").unwrap_or(&msg);
            eprintln!("error: {msg} (see `cvfarm --help`)");
            ExitCode::from(EXIT_USAGE)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cause_chain_is_one_line() {
        let e = anyhow::anyhow!("line one\nline two").context("loading scene.json");
        assert_eq!(one_line(&e), "loading scene.json: line one line two");
    }

    /// Regression: a missing scene file printed the OS error twice (once in the scene
    /// error's own message, once as its source).
    #[test]
    fn a_cause_already_in_the_message_is_not_repeated() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "No such file");
        #[derive(Debug)]
        struct Wrapped(std::io::Error);
        impl std::fmt::Display for Wrapped {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                write!(f, "nope.json: {}", self.0)
            }
        }
        impl std::error::Error for Wrapped {
            fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
                Some(&self.0)
            }
        }
        let e = anyhow::Error::new(Wrapped(io)).context("loading nope.json");
        assert_eq!(one_line(&e), "loading nope.json: nope.json: No such file");
    }
}
