//! The reference servers the twin is measured against, each run as a child
//! process of the benchmark exactly like `twin serve`: a bare echo over TCP
//! and over a pseudo-terminal (the floor any server's latency sits on), the
//! TCP echo again on tokio (the cost of a readiness loop by itself), and a
//! tokio-modbus 0.17 TCP server shaped like that crate's `tcp-server` example.

use crate::pty::open_raw;
use anyhow::{Context, Result};
use std::future::{Ready, ready};
use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::sync::{Arc, Mutex};
use tokio_modbus::prelude::*;
use tokio_modbus::server::Service;
use tokio_modbus::server::tcp::{Server, accept_tcp_connection};

fn announce(protocol: &str, address: &str) {
    println!("  {protocol} {address}");
    println!("ready");
}

fn echo_stream(mut stream: impl Read + Write) {
    let mut buf = [0u8; 4096];
    loop {
        match stream.read(&mut buf) {
            Ok(0) | Err(_) => return,
            Ok(n) => {
                if stream.write_all(&buf[..n]).is_err() {
                    return;
                }
            }
        }
    }
}

/// Echo every byte back on each accepted connection, one thread each.
pub fn echo_tcp() -> Result<()> {
    let listener = TcpListener::bind("127.0.0.1:0").context("binding the echo server")?;
    announce("echo-tcp", &format!("tcp://{}", listener.local_addr()?));
    for stream in listener.incoming() {
        let Ok(stream) = stream else { continue };
        let _ = stream.set_nodelay(true);
        std::thread::spawn(move || echo_stream(stream));
    }
    Ok(())
}

/// Echo every byte back on the terminal at `path`.
pub fn echo_pty(path: &Path) -> Result<()> {
    let port = open_raw(path)?;
    announce("echo-pty", &path.display().to_string());
    echo_stream(port);
    Ok(())
}

/// The module's register counts (docs/protocols/modbus-map.md), so both servers answer
/// the same requests with the same amount of data.
const INPUT_REGISTERS: usize = 10;
const HOLDING_REGISTERS: usize = 3;

#[derive(Debug)]
struct Registers {
    input: [u16; INPUT_REGISTERS],
    holding: [u16; HOLDING_REGISTERS],
}

#[derive(Debug, Clone)]
struct ModbusService(Arc<Mutex<Registers>>);

fn window(len: usize, addr: u16, count: u16) -> Result<std::ops::Range<usize>, ExceptionCode> {
    let start = usize::from(addr);
    let end = start + usize::from(count);
    if count == 0 || end > len {
        Err(ExceptionCode::IllegalDataAddress)
    } else {
        Ok(start..end)
    }
}

impl Service for ModbusService {
    type Request = Request<'static>;
    type Response = Response;
    type Exception = ExceptionCode;
    type Future = Ready<Result<Response, ExceptionCode>>;

    fn call(&self, req: Self::Request) -> Self::Future {
        let mut regs = self.0.lock().expect("no panics while locked");
        let reply = match req {
            Request::ReadInputRegisters(addr, count) => window(INPUT_REGISTERS, addr, count)
                .map(|r| Response::ReadInputRegisters(regs.input[r].to_vec())),
            Request::ReadHoldingRegisters(addr, count) => window(HOLDING_REGISTERS, addr, count)
                .map(|r| Response::ReadHoldingRegisters(regs.holding[r].to_vec())),
            Request::WriteSingleRegister(addr, value) => {
                window(HOLDING_REGISTERS, addr, 1).map(|r| {
                    regs.holding[r.start] = value;
                    Response::WriteSingleRegister(addr, value)
                })
            }
            _ => Err(ExceptionCode::IllegalFunction),
        };
        ready(reply)
    }
}

/// A multi-threaded runtime, as the tokio-modbus examples use.
fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_io()
        .build()
        .context("starting tokio")
}

/// A tokio-modbus TCP server on a multi-threaded runtime, as in its example.
pub fn tokio_modbus_tcp() -> Result<()> {
    let runtime = runtime()?;
    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        announce("modbus-tcp", &format!("tcp://{}", listener.local_addr()?));
        let service = service();
        let server = Server::new(listener);
        let on_connected = |stream: tokio::net::TcpStream, addr| {
            let service = service.clone();
            async move {
                let _ = stream.set_nodelay(true);
                accept_tcp_connection(stream, addr, move |_| Ok(Some(service.clone())))
            }
        };
        server
            .serve(&on_connected, |err| eprintln!("tokio-modbus: {err}"))
            .await?;
        anyhow::Ok(())
    })
}

/// The tokio-modbus RTU server on the terminal at `path` (tokio-serial).
pub fn tokio_modbus_rtu(path: &Path) -> Result<()> {
    let runtime = runtime()?;
    runtime.block_on(async {
        let port =
            tokio_serial::SerialStream::open(&tokio_serial::new(path.to_string_lossy(), 115_200))
                .with_context(|| format!("opening {}", path.display()))?;
        announce("modbus-rtu", &path.display().to_string());
        tokio_modbus::server::rtu::Server::new(port)
            .serve_forever(service())
            .await?;
        anyhow::Ok(())
    })
}

fn service() -> ModbusService {
    ModbusService(Arc::new(Mutex::new(Registers {
        input: std::array::from_fn(|i| 1000 + i as u16),
        holding: [0; HOLDING_REGISTERS],
    })))
}

/// Connects with Nagle off: every request goes out as one segment at once.
pub fn connect(addr: &str) -> Result<TcpStream> {
    let stream = TcpStream::connect(addr).with_context(|| format!("connecting to {addr}"))?;
    stream.set_nodelay(true)?;
    Ok(stream)
}

/// The echo on a multi-threaded tokio runtime, a task per connection: the
/// readiness loop's own cost, beside the thread-per-connection echo's.
pub fn echo_tokio() -> Result<()> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let runtime = runtime()?;
    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        announce("echo-tcp", &format!("tcp://{}", listener.local_addr()?));
        loop {
            let Ok((mut stream, _)) = listener.accept().await else {
                continue;
            };
            let _ = stream.set_nodelay(true);
            tokio::spawn(async move {
                let mut buf = [0u8; 4096];
                while let Ok(n @ 1..) = stream.read(&mut buf).await {
                    if stream.write_all(&buf[..n]).await.is_err() {
                        return;
                    }
                }
            });
        }
    })
}
