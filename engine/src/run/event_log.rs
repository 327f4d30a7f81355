//! `runs/<id>/events.jsonl`: one JSON object per line, flushed as written, so a killed run
//! leaves a readable log. With `--json` each line is echoed to stdout.

use std::fs::File;
use std::io::Write;
use std::path::Path;
use std::time::Instant;

use anyhow::Context as _;

use crate::event::{Event, Logged};

pub struct EventLog {
    file: File,
    echo: bool,
    clock: Instant,
}

impl EventLog {
    /// Creates the run's directory with its `logs/`, and its event log.
    pub fn create(run_dir: &Path, echo: bool) -> anyhow::Result<EventLog> {
        std::fs::create_dir_all(run_dir.join("logs"))?;
        let path = run_dir.join("events.jsonl");
        let file = File::create(&path).with_context(|| format!("creating {}", path.display()))?;
        Ok(EventLog { file, echo, clock: Instant::now() })
    }

    pub fn write(&mut self, event: Event) -> anyhow::Result<()> {
        let t = (self.clock.elapsed().as_secs_f64() * 1000.0).round() / 1000.0;
        let mut line = serde_json::to_string(&Logged { event, t })?;
        line.push('\n');
        // One write a line: a killed run leaves whole lines.
        self.file.write_all(line.as_bytes())?;
        if self.echo {
            print!("{line}");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_event_is_one_whole_line_read_back_as_written() {
        let dir = std::env::temp_dir().join(format!("rlmflow-events-{}", std::process::id()));
        let run_dir = dir.join("runs/r1");
        let mut log = EventLog::create(&run_dir, false).unwrap();
        assert!(run_dir.join("logs").is_dir());
        log.write(Event::RemoteDown { remote: "s3://b".into(), why: "refused".into() }).unwrap();
        log.write(Event::OperatorEvent { stage: "a".into(), name: "n".into(), data: serde_json::json!({"x": 1}) }).unwrap();
        let text = std::fs::read_to_string(run_dir.join("events.jsonl")).unwrap();
        let lines: Vec<serde_json::Value> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
        assert_eq!(lines.len(), 2);
        assert_eq!(lines[0]["event"], "remote_down", "{text}");
        assert_eq!(lines[1]["data"]["x"], 1, "{text}");
        assert!(lines[1]["t"].as_f64().unwrap() >= lines[0]["t"].as_f64().unwrap());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
