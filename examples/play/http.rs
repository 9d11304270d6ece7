//! The little HTTP `play` speaks: one request head read with blocking reads against a deadline,
//! a reply that closes the connection cleanly, and the WebSocket upgrade done by hand so that the
//! bytes are read once and the socket gets `play`'s limits.

use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, TcpStream};
use std::time::{Duration, Instant};
use tungstenite::handshake::derive_accept_key;
use tungstenite::protocol::{Role, WebSocketConfig};
use tungstenite::WebSocket;

/// The largest request head read; a longer one is answered 431.
pub const MAX_HEAD: usize = 8192;
/// The largest WebSocket message (and frame) a page may send: its messages are a dozen bytes
/// (`keys -1 1`, `reset`, `sample`), so anything near this is not the page.
pub const MAX_MESSAGE: usize = 256;

/// A request head: the request line's method and path, and the header fields.
pub struct Request {
    pub method: String,
    pub path: String,
    headers: Vec<(String, String)>,
    /// Bytes read past the head (a client that did not wait for the answer).
    pub rest: Vec<u8>,
}

/// Why no request came.
pub enum HeadError {
    /// No blank line within [`MAX_HEAD`] bytes: 431.
    TooLarge,
    /// Not an HTTP/1 request head: 400, with the reason.
    Malformed(&'static str),
    /// Closed, timed out or failed before a whole head: nothing to answer.
    Gone(String),
}

impl Request {
    /// The first header field named `name` (case-insensitive), trimmed.
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }

    /// Whether the header field `name` lists `token` (comma-separated, case-insensitive).
    fn lists(&self, name: &str, token: &str) -> bool {
        self.header(name)
            .is_some_and(|v| v.split(',').any(|t| t.trim().eq_ignore_ascii_case(token)))
    }
}

/// Reads one request head with blocking reads, all within `deadline` from now: a client that
/// sends slowly or not at all costs a sleeping thread until then, never a polling one.
pub fn read_request(stream: &mut TcpStream, deadline: Duration) -> Result<Request, HeadError> {
    let start = Instant::now();
    let mut buf = [0u8; MAX_HEAD];
    let mut len = 0;
    let end = loop {
        if let Some(at) = buf[..len].windows(4).position(|w| w == b"\r\n\r\n") {
            break at;
        }
        if len == buf.len() {
            return Err(HeadError::TooLarge);
        }
        let left = deadline
            .checked_sub(start.elapsed())
            .filter(|d| !d.is_zero())
            .ok_or_else(|| HeadError::Gone("no request head in time".into()))?;
        stream
            .set_read_timeout(Some(left))
            .map_err(|e| HeadError::Gone(e.to_string()))?;
        match stream.read(&mut buf[len..]) {
            Ok(0) => return Err(HeadError::Gone("closed before a whole request".into())),
            Ok(n) => len += n,
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(e) => return Err(HeadError::Gone(e.to_string())),
        }
    };
    let head = std::str::from_utf8(&buf[..end]).map_err(|_| HeadError::Malformed("not UTF-8"))?;
    let mut lines = head.split("\r\n");
    let mut words = lines.next().unwrap_or("").split(' ');
    let (Some(method), Some(path), Some(version), None) = (words.next(), words.next(), words.next(), words.next())
    else {
        return Err(HeadError::Malformed("not a request line"));
    };
    if method.is_empty() || !path.starts_with('/') || !version.starts_with("HTTP/1.") {
        return Err(HeadError::Malformed("not an HTTP/1 request line"));
    }
    let mut headers = Vec::new();
    for line in lines {
        let (name, value) = line
            .split_once(':')
            .ok_or(HeadError::Malformed("a header line without ':'"))?;
        if name.is_empty() || name.contains(|c: char| c.is_ascii_whitespace()) {
            return Err(HeadError::Malformed("a malformed header name"));
        }
        headers.push((name.to_string(), value.trim().to_string()));
    }
    let request = Request {
        method: method.to_string(),
        path: path.to_string(),
        headers,
        rest: buf[end + 4..len].to_vec(),
    };
    if request.header("content-length").is_some_and(|n| n != "0") || request.header("transfer-encoding").is_some() {
        return Err(HeadError::Malformed("a request with a body"));
    }
    Ok(request)
}

/// Answers `status` with a body and closes: the write side first, then whatever the client still
/// sends is read and dropped (for at most a second), so that the close is a FIN, not a reset
/// that could discard the answer before the client read it.
pub fn reply(mut stream: TcpStream, status: &str, kind: &str, body: &str) -> Result<(), String> {
    let head = format!(
        "HTTP/1.1 {status}\r\nContent-Type: {kind}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    stream
        .set_write_timeout(Some(Duration::from_secs(5)))
        .map_err(|e| e.to_string())?;
    stream
        .write_all(head.as_bytes())
        .and_then(|()| stream.write_all(body.as_bytes()))
        .map_err(|e| e.to_string())?;
    linger(stream);
    Ok(())
}

/// Shuts the write side and drains what the client sends until it closes (at most a second and
/// 64 KiB), then drops the socket.
pub fn linger(mut stream: TcpStream) {
    let _ = stream.shutdown(Shutdown::Write);
    let _ = stream.set_read_timeout(Some(Duration::from_secs(1)));
    let mut sink = [0u8; 4096];
    for _ in 0..16 {
        if !matches!(stream.read(&mut sink), Ok(n) if n > 0) {
            break;
        }
    }
}

/// Whether the request asks for a WebSocket (RFC 6455, section 4.2.1).
pub fn is_upgrade(request: &Request) -> bool {
    request.method == "GET"
        && request.lists("upgrade", "websocket")
        && request.lists("connection", "upgrade")
        && request.header("sec-websocket-version") == Some("13")
        && request.header("sec-websocket-key").is_some()
}

/// Accepts the upgrade (`is_upgrade` holds): the 101 answer, then the WebSocket with messages
/// bounded to [`MAX_MESSAGE`] and a small read buffer.
pub fn upgrade(mut stream: TcpStream, request: Request) -> Result<WebSocket<TcpStream>, String> {
    let key = request.header("sec-websocket-key").unwrap_or("");
    let answer = format!(
        "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Accept: {}\r\n\r\n",
        derive_accept_key(key.as_bytes())
    );
    stream.write_all(answer.as_bytes()).map_err(|e| e.to_string())?;
    let config = WebSocketConfig::default()
        .max_message_size(Some(MAX_MESSAGE))
        .max_frame_size(Some(MAX_MESSAGE))
        .read_buffer_size(4096);
    Ok(WebSocket::from_partially_read(
        stream,
        request.rest,
        Role::Server,
        Some(config),
    ))
}

/// `text` for a log line: at most 40 characters, escaped, with its length when cut.
pub fn short(text: &str) -> String {
    let cut: String = text.chars().take(40).collect();
    if cut.len() == text.len() {
        format!("{cut:?}")
    } else {
        format!("{cut:?}... ({} bytes)", text.len())
    }
}
