// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// Everything of the burrforce C++ SDK (header-only, C++17, no dependencies).
#pragma once

#include "burrforce/client.hpp"
#include "burrforce/clock.hpp"
#include "burrforce/connection.hpp"
#include "burrforce/frames.hpp"
#include "burrforce/hmac.hpp"
#include "burrforce/http.hpp"
#include "burrforce/json.hpp"
#include "burrforce/mesh.hpp"
#include "burrforce/mesh_sync.hpp"
#include "burrforce/messages.hpp"
#include "burrforce/msgpack.hpp"
#include "burrforce/protocol.hpp"
#include "burrforce/rest.hpp"
#include "burrforce/sequence.hpp"
#include "burrforce/session.hpp"
#include "burrforce/sha256.hpp"
#include "burrforce/streamer.hpp"
#include "burrforce/udp_socket.hpp"
