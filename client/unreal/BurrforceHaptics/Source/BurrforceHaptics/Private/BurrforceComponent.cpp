// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The game-thread side only: connect (on a worker), publish the tool's transform each tick,
// copy the streamer's newest state into Blueprint properties. The haptic loop is the core's
// Streamer thread; nothing here runs at 1 kHz.

#include "BurrforceComponent.h"

#include "Async/Async.h"
#include "BurrforceCore.h"
#include "Components/SceneComponent.h"
#include "GameFramework/Actor.h"

#include <atomic>
#include <memory>
#include <mutex>
#include <vector>

/// What outlives a tick: shared with the connecting worker and the stream thread's
/// callbacks, so neither ever touches the UObject.
struct FBurrforceRuntime
{
	std::unique_ptr<burrforce::Streamer> Streamer;
	std::string RestUrl;
	std::string Token;
	uint32 Session = 0;
	bool bCreatedHere = false;
	std::atomic<bool> bReady{false};
	std::atomic<bool> bStopping{false};
	TFuture<void> Connecting;

	// NOTICEs, handed from the stream thread to the game thread (bounded, no allocation
	// once reserved).
	std::mutex NoticeMutex;
	std::vector<uint16> Notices;
};

UBurrforceComponent::UBurrforceComponent()
{
	PrimaryComponentTick.bCanEverTick = true;
	// Before physics, so AddForce in this frame uses the newest force.
	PrimaryComponentTick.TickGroup = TG_PrePhysics;
}

void UBurrforceComponent::BeginPlay()
{
	Super::BeginPlay();
	StartStreaming();
}

void UBurrforceComponent::StartStreaming()
{
	Runtime = MakeShared<FBurrforceRuntime, ESPMode::ThreadSafe>();
	Runtime->Notices.reserve(64);
	// Copies of the settings: the worker must not read UPROPERTYs.
	const EBurrforceConnectMode Mode = ConnectMode;
	const std::string Url = BurrforceUE::ToStd(RestUrl), Tok = BurrforceUE::ToStd(Token);
	const std::string Bone = BurrforceUE::ToStd(BoneSource);
	const std::string HostS = BurrforceUE::ToStd(Host), Key = BurrforceUE::ToStd(KeyHex);
	const std::string ConnPath = BurrforceUE::ToStd(ConnectionFile);
	const uint16 Port = static_cast<uint16>(UdpPort);
	const uint32 Sid = static_cast<uint32>(SessionId);
	const double Rate = RateHz;
	TSharedPtr<FBurrforceRuntime, ESPMode::ThreadSafe> R = Runtime;

	// REST and file I/O block: never on the game thread.
	R->Connecting = Async(EAsyncExecution::Thread, [=]()
	{
		try
		{
			burrforce::StreamerConfig Cfg;
			Cfg.rate_hz = Rate;
			if (Mode == EBurrforceConnectMode::CreateSession)
			{
				burrforce::Rest Rest(Url, Tok);
				burrforce::SessionInfo S = Rest.create_session(Bone, "unreal");
				Cfg.host = S.udp_host;
				Cfg.port = S.udp_port;
				Cfg.session = S.id;
				Cfg.key = S.key;
				R->RestUrl = Url;
				R->Token = Tok;
				R->bCreatedHere = true;
			}
			else if (Mode == EBurrforceConnectMode::ConnectionFile)
			{
				burrforce::Connection C = ConnPath.empty()
					? burrforce::Connection::read()
					: burrforce::Connection::read(ConnPath);
				if (C.frame != "unreal")
				{
					UE_LOG(LogBurrforce, Warning,
						TEXT("burrforce session %u has frame %s, not unreal: positions will "
							"be misread (start the server with --frame unreal)"),
						C.session, *BurrforceUE::ToUE(C.frame));
				}
				Cfg.host = C.host;
				Cfg.port = C.udp_port;
				Cfg.session = C.session;
				Cfg.key = C.key;
				R->RestUrl = C.http_url;
				R->Token = C.token;
			}
			else
			{
				Cfg.host = HostS;
				Cfg.port = Port;
				Cfg.session = Sid;
				if (!Key.empty() && !burrforce::parse_hex(Key, Cfg.key))
				{
					throw std::runtime_error("KeyHex is not hex");
				}
			}
			R->Session = Cfg.session;
			auto S = std::make_unique<burrforce::Streamer>(Cfg);
			FBurrforceRuntime* Raw = R.Get();
			S->on_notice([Raw](const burrforce::Event& Ev)
			{
				// Every hello in flight is answered, and every POSE in flight on a closed
				// stream refused: only the notice that moved the stream is news.
				const uint16 Code = Ev.notice.error;
				if ((Code == burrforce::NEW_STREAM || Code == burrforce::WRONG_STREAM)
					&& !Ev.stream_changed)
				{
					return;
				}
				std::lock_guard<std::mutex> Lock(Raw->NoticeMutex);
				if (Raw->Notices.size() < Raw->Notices.capacity())
				{
					Raw->Notices.push_back(Code);
				}
			});
			if (R->bStopping)
			{
				return;
			}
			S->start();
			R->Streamer = std::move(S);
			R->bReady = !R->bStopping;
			UE_LOG(LogBurrforce, Log, TEXT("burrforce: streaming to %s:%u session %u at %.0f Hz"),
				*BurrforceUE::ToUE(Cfg.host), Cfg.port, Cfg.session, Rate);
		}
		catch (const std::exception& E)
		{
			UE_LOG(LogBurrforce, Error, TEXT("burrforce: cannot connect: %s"),
				*BurrforceUE::ToUE(E.what()));
		}
	});
}

void UBurrforceComponent::EndPlay(const EEndPlayReason::Type EndPlayReason)
{
	if (Runtime.IsValid())
	{
		// Everything left may block: the connect worker can be inside create_session (up to
		// its load timeout) or a TCP connect, and deleting the session is a REST call. The
		// game thread only raises the flag and hands the runtime to a clean-up worker, which
		// owns it from here on; nothing it does touches this UObject.
		TSharedPtr<FBurrforceRuntime, ESPMode::ThreadSafe> R = MoveTemp(Runtime);
		R->bStopping = true;
		Async(EAsyncExecution::Thread, [R = MoveTemp(R)]()
		{
			R->Connecting.Wait();
			if (R->Streamer)
			{
				R->Streamer->stop();
			}
			if (R->bCreatedHere)
			{
				try
				{
					burrforce::Rest(R->RestUrl, R->Token).delete_session(R->Session);
				}
				catch (const std::exception& E)
				{
					UE_LOG(LogBurrforce, Warning, TEXT("burrforce: deleting session %u: %s"),
						R->Session, *BurrforceUE::ToUE(E.what()));
				}
			}
		});
	}
	Super::EndPlay(EndPlayReason);
}

void UBurrforceComponent::TickComponent(float DeltaTime, ELevelTick TickType,
	FActorComponentTickFunction* ThisTickFunction)
{
	Super::TickComponent(DeltaTime, TickType, ThisTickFunction);
	if (!Runtime.IsValid() || !Runtime->bReady)
	{
		return;
	}
	if (ActiveSessionId == 0)
	{
		ActiveSessionId = static_cast<int32>(Runtime->Session);
		OnConnected.Broadcast(ActiveSessionId, Runtime->bCreatedHere);
	}
	PublishPose();
	ReadState();
}

void UBurrforceComponent::PublishPose()
{
	const USceneComponent* T = Tool ? Tool.Get()
		: (GetOwner() ? GetOwner()->GetRootComponent() : nullptr);
	if (!T)
	{
		return;
	}
	burrforce::ToolPose P;
	P.position = BurrforceUE::ToCore(T->GetComponentLocation());  // cm, world
	P.orientation = BurrforceUE::ToCore(T->GetComponentQuat());
	P.rpm = Rpm;
	P.spindle_on = bSpindleOn;
	P.flags = bNoCarve ? burrforce::FLAG_NO_CARVE : 0u;
	Runtime->Streamer->publish(P);  // stamped now: when the engine sampled it
}

void UBurrforceComponent::ReadState()
{
	const burrforce::HapticState S = Runtime->Streamer->state();
	if (Runtime->Streamer->failed() && !bReportedFailure)
	{
		// The stream thread caught an exception (state() is zero from now on): say why once.
		bReportedFailure = true;
		UE_LOG(LogBurrforce, Error, TEXT("burrforce: the stream stopped: %s"),
			*BurrforceUE::ToUE(Runtime->Streamer->failure()));
	}
	ForceN = BurrforceUE::ToUE(S.force);
	ForceForAddForce = ForceN * 100.0;  // N → kg·cm/s² (SPEC 6.3)
	TorqueNcm = BurrforceUE::ToUE(S.torque);
	TorqueForAddTorque = TorqueNcm * 100.0;
	ResistiveN = BurrforceUE::ToUE(S.resistive);
	VibrationAmplitudeN = static_cast<float>(S.vibration_amplitude_N);
	VibrationFrequencyHz = static_cast<float>(S.vibration_frequency_hz);
	VibrationAxis = BurrforceUE::ToUE(S.vibration_axis);
	Status = static_cast<int32>(S.status);
	bCutting = (S.status & burrforce::STATUS_CUTTING) != 0;
	bContact = (S.status & burrforce::STATUS_CONTACT) != 0;
	bForceValid = S.valid;
	ProxyPosition = BurrforceUE::ToUE(S.proxy_position);
	CouplingStiffness = static_cast<float>(S.coupling_stiffness);
	BoneVersion = static_cast<int64>(S.bone_version);
	RemovedTotalMm3 = static_cast<float>(S.removed_total_mm3);
	RoundTripMs = static_cast<float>(S.rtt_us) / 1000.f;
	const burrforce::Counters& C = Runtime->Streamer->counters();
	PosesSent = static_cast<int64>(C.sent.load());
	RepliesReceived = static_cast<int64>(C.replies.load());
	StreamId = static_cast<int64>(Runtime->Streamer->stream());

	OnForce.Broadcast(ForceN, ForceForAddForce);
	if (Status != LastStatus)
	{
		LastStatus = Status;
		OnStatusChanged.Broadcast(Status);
	}
	std::vector<uint16> Notices;
	{
		std::lock_guard<std::mutex> Lock(Runtime->NoticeMutex);
		if (!Runtime->Notices.empty())
		{
			Notices.swap(Runtime->Notices);
			Runtime->Notices.reserve(64);  // the stream thread never allocates
		}
	}
	for (uint16 Code : Notices)
	{
		OnNotice.Broadcast(Code, FString(burrforce::error_name(Code)));
	}
}

void UBurrforceComponent::RestartStream()
{
	if (Runtime.IsValid() && Runtime->bReady)
	{
		Runtime->Streamer->restart_stream();
	}
}

bool UBurrforceComponent::IsStreaming() const
{
	return Runtime.IsValid() && Runtime->bReady && Runtime->Streamer->running();
}

uint64 UBurrforceComponent::GetLatestBoneVersion() const
{
	return Runtime.IsValid() && Runtime->bReady ? Runtime->Streamer->bone_version() : 0;
}

TFunction<uint64()> UBurrforceComponent::MakeBoneVersionSource() const
{
	TSharedPtr<FBurrforceRuntime, ESPMode::ThreadSafe> R = Runtime;
	return [R]() -> uint64
	{
		return R.IsValid() && R->bReady ? R->Streamer->bone_version() : 0;
	};
}

bool UBurrforceComponent::GetRestAccess(FString& OutUrl, FString& OutToken,
	int32& OutSession) const
{
	if (!Runtime.IsValid() || !Runtime->bReady || Runtime->RestUrl.empty())
	{
		return false;
	}
	OutUrl = BurrforceUE::ToUE(Runtime->RestUrl);
	OutToken = BurrforceUE::ToUE(Runtime->Token);
	OutSession = static_cast<int32>(Runtime->Session);
	return true;
}
