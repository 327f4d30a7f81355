//! A fake OpenAI-compatible chat-completions endpoint on loopback: what the `llm` operator's
//! tests talk to. Each request is answered by the test's own function; the server counts the
//! requests and keeps their bodies.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use serde_json::Value;

/// One chat-completions request as the endpoint received it.
pub struct Request {
    /// 0 for the first request the server received.
    pub number: usize,
    pub body: Value,
    /// The `Authorization` header's value (`Bearer sk-...`), empty without one.
    pub authorization: String,
}

impl Request {
    /// The user message: the prompt the operator wrote.
    pub fn prompt(&self) -> &str {
        self.body["messages"][1]["content"].as_str().unwrap_or_default()
    }

    /// How many completions it asks for (`n`).
    pub fn n(&self) -> usize {
        self.body["n"].as_u64().unwrap_or(1) as usize
    }
}

/// What the endpoint answers.
pub struct Response {
    pub status: u16,
    pub body: String,
    /// Sends `Retry-After: 0`, as a rate limit or an overloaded server does.
    pub retry_after: bool,
}

impl Response {
    /// 200 with this JSON body.
    pub fn json(body: &Value) -> Response {
        Response { status: 200, body: body.to_string(), retry_after: false }
    }

    /// 200 with `captions` as its choices, and token usage.
    pub fn captions(captions: &[String]) -> Response {
        let choices: Vec<Value> =
            captions.iter().enumerate().map(|(i, c)| serde_json::json!({"index": i, "message": {"role": "assistant", "content": c}})).collect();
        Response::json(&serde_json::json!({"choices": choices, "usage": {"prompt_tokens": 700, "completion_tokens": 150 * captions.len()}}))
    }

    /// An API error with OpenAI's body, and `Retry-After: 0`.
    pub fn error(status: u16, message: &str) -> Response {
        Response { status, body: serde_json::json!({"error": {"message": message}}).to_string(), retry_after: true }
    }
}

pub struct FakeOpenAi {
    /// The API root to give as `base_url`: `http://127.0.0.1:PORT/v1`.
    pub url: String,
    requests: Arc<AtomicUsize>,
    bodies: Arc<Mutex<Vec<Value>>>,
}

type Answer = dyn Fn(&Request) -> Response + Send + Sync;

impl FakeOpenAi {
    /// Serves until the test process ends, answering each request with `answer`.
    pub fn start(answer: impl Fn(&Request) -> Response + Send + Sync + 'static) -> FakeOpenAi {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}/v1", listener.local_addr().unwrap());
        let (requests, bodies) = (Arc::new(AtomicUsize::new(0)), Arc::new(Mutex::new(Vec::new())));
        let answer: Arc<Answer> = Arc::new(answer);
        let (r, b) = (requests.clone(), bodies.clone());
        std::thread::spawn(move || {
            for stream in listener.incoming().flatten() {
                let (r, b, answer) = (r.clone(), b.clone(), answer.clone());
                std::thread::spawn(move || serve(stream, &r, &b, &*answer));
            }
        });
        FakeOpenAi { url, requests, bodies }
    }

    /// Requests received so far.
    pub fn requests(&self) -> usize {
        self.requests.load(Ordering::SeqCst)
    }

    /// The bodies of the requests received so far, in order.
    pub fn bodies(&self) -> Vec<Value> {
        self.bodies.lock().unwrap().clone()
    }
}

/// Answers the requests of one keep-alive connection until the client closes it.
fn serve(mut stream: TcpStream, requests: &AtomicUsize, bodies: &Mutex<Vec<Value>>, answer: &Answer) {
    let mut reader = BufReader::new(stream.try_clone().unwrap());
    loop {
        let (mut length, mut authorization) = (0, String::new());
        loop {
            let mut line = String::new();
            if reader.read_line(&mut line).unwrap_or(0) == 0 {
                return;
            }
            let line = line.trim_end();
            if line.is_empty() {
                break;
            }
            let lower = line.to_ascii_lowercase();
            if let Some(v) = lower.strip_prefix("content-length:") {
                length = v.trim().parse().unwrap();
            }
            if lower.starts_with("authorization:") {
                authorization = line["authorization:".len()..].trim().to_owned();
            }
        }
        let mut body = vec![0; length];
        if reader.read_exact(&mut body).is_err() {
            return;
        }
        let body: Value = serde_json::from_slice(&body).unwrap_or(Value::Null);
        bodies.lock().unwrap().push(body.clone());
        let request = Request { number: requests.fetch_add(1, Ordering::SeqCst), body, authorization };
        let response = answer(&request);
        let retry = if response.retry_after { "Retry-After: 0\r\n" } else { "" };
        let head =
            format!("HTTP/1.1 {} X\r\nContent-Type: application/json\r\nContent-Length: {}\r\n{retry}\r\n", response.status, response.body.len());
        if stream.write_all(head.as_bytes()).and_then(|()| stream.write_all(response.body.as_bytes())).is_err() {
            return;
        }
    }
}
