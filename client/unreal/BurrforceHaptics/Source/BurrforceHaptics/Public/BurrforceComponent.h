// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// Streams a tool's pose to a burrforce server at a fixed rate (1 kHz by default) from a
// background thread, and exposes the forces it answers with. Unreal frame `unreal`: cm,
// left-handed, the FQuat sent as is. Thin by design: the logic is the header-only core
// (client/cpp/include), tested outside the engine.

#pragma once

#include "Components/ActorComponent.h"
#include "CoreMinimal.h"
#include "BurrforceComponent.generated.h"

DECLARE_DYNAMIC_MULTICAST_DELEGATE_TwoParams(FBurrforceForceEvent, FVector, ForceN,
	FVector, ForceForAddForce);
DECLARE_DYNAMIC_MULTICAST_DELEGATE_OneParam(FBurrforceStatusEvent, int32, Status);
DECLARE_DYNAMIC_MULTICAST_DELEGATE_TwoParams(FBurrforceNoticeEvent, int32, ErrorCode,
	FString, ErrorName);
DECLARE_DYNAMIC_MULTICAST_DELEGATE_TwoParams(FBurrforceConnectedEvent, int32, SessionId,
	bool, bCreatedHere);

struct FBurrforceRuntime;

UENUM(BlueprintType)
enum class EBurrforceConnectMode : uint8
{
	/// Create a session of frame `unreal` over REST (RestUrl + Token); deleted at EndPlay.
	CreateSession,
	/// Use an existing session: Host, UdpPort, SessionId, KeyHex (e.g. `burrforce serve
	/// --frame unreal` prints them).
	ExistingSession,
	/// Read the connection file `burrforce serve` writes (ConnectionFile, or its default).
	ConnectionFile,
};

UCLASS(ClassGroup = (Haptics), meta = (BlueprintSpawnableComponent),
	HideCategories = (Activation, Cooking, Collision))
class BURRFORCEHAPTICS_API UBurrforceComponent : public UActorComponent
{
	GENERATED_BODY()

public:
	UBurrforceComponent();

	// --- Connection -------------------------------------------------------------------
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Connection")
	EBurrforceConnectMode ConnectMode = EBurrforceConnectMode::ConnectionFile;

	/// REST URL without /v1, e.g. http://127.0.0.1:8000 (CreateSession).
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Connection")
	FString RestUrl;

	/// REST bearer token (CreateSession). Keep it out of shipped builds.
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Connection")
	FString Token;

	/// The bone of a created session: phantom:NAME, library:PATH, snapshot:NAME.
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Connection")
	FString BoneSource = TEXT("phantom:workpiece");

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Connection")
	FString Host = TEXT("127.0.0.1");

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Connection")
	int32 UdpPort = 47810;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Connection")
	int32 SessionId = 1;

	/// The session key in hex (64 digits); empty only for a --no-auth loopback server.
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Connection")
	FString KeyHex;

	/// Empty: $BURRFORCE_CONNECTION, else the server's default location.
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Connection")
	FString ConnectionFile;

	/// POSEs per second, sent from a background thread whatever the frame rate.
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Connection",
		meta = (ClampMin = "10", ClampMax = "4000"))
	float RateHz = 1000.f;

	// --- Tool --------------------------------------------------------------------------
	/// The burr: its world location is the burr centre, its rotation turns the session's
	/// local tool axis (+Z by default, toward the handle). None: the owner's root.
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Tool")
	TObjectPtr<USceneComponent> Tool;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Tool")
	float Rpm = 60000.f;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Tool")
	bool bSpindleOn = true;

	/// Evaluate forces without removing bone.
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Tool")
	bool bNoCarve = false;

	// --- Output (updated every tick from the newest good REPLY) ---------------------------
	/// What the hand should feel, N, Unreal axes. Zero when no good REPLY for 50 ms.
	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	FVector ForceN = FVector::ZeroVector;

	/// ForceN × 100: kg·cm/s², what UPrimitiveComponent::AddForce takes (SPEC 6.3).
	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	FVector ForceForAddForce = FVector::ZeroVector;

	/// Reaction torque on the burr, N·cm, Unreal axes.
	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	FVector TorqueNcm = FVector::ZeroVector;

	/// TorqueNcm × 100: what AddTorqueInRadians takes.
	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	FVector TorqueForAddTorque = FVector::ZeroVector;

	/// Cutting force as (feed, lateral, normal), N.
	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	FVector ResistiveN = FVector::ZeroVector;

	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	float VibrationAmplitudeN = 0.f;

	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	float VibrationFrequencyHz = 0.f;

	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	FVector VibrationAxis = FVector::ZeroVector;

	/// REPLY status bits (1 cutting, 2 contact, 4 forbidden, 8 clamped, 16 stale, 32 shaft
	/// contact, 64 slow spindle).
	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	int32 Status = 0;

	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	bool bCutting = false;

	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	bool bContact = false;

	/// A good REPLY arrived within the last 50 ms.
	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	bool bForceValid = false;

	/// Where the burr is and cuts in the coupled output (cm); zero in raw output.
	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	FVector ProxyPosition = FVector::ZeroVector;

	/// N/cm; 0 = raw output (render ForceN).
	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	float CouplingStiffness = 0.f;

	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	int64 BoneVersion = 0;

	/// Bone removed since BeginPlay, mm³.
	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	float RemovedTotalMm3 = 0.f;

	/// Send to reply (network plus server time); not including how old the published pose
	/// was, which SPEC 5.5's rtt would add (up to one frame).
	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	float RoundTripMs = 0.f;

	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	int64 PosesSent = 0;

	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	int64 RepliesReceived = 0;

	/// The session streamed to (after connecting).
	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	int32 ActiveSessionId = 0;

	/// The stream number the server handed out (protocol v2), 0 while asking for one. A
	/// new number after a server restart or a REST restart-stream: the component asked
	/// for it by itself.
	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Output")
	int64 StreamId = 0;

	UPROPERTY(BlueprintAssignable, Category = "Burrforce")
	FBurrforceForceEvent OnForce;

	UPROPERTY(BlueprintAssignable, Category = "Burrforce")
	FBurrforceStatusEvent OnStatusChanged;

	/// A NOTICE (UNKNOWN_SESSION, BAD_TAG: the key is wrong, BAD_VERSION: the server does
	/// not speak protocol v2, ...): a diagnostic, not a force. Of the stream handshake's
	/// notices only those that gave or took the stream (NEW_STREAM, WRONG_STREAM) are passed.
	UPROPERTY(BlueprintAssignable, Category = "Burrforce")
	FBurrforceNoticeEvent OnNotice;

	UPROPERTY(BlueprintAssignable, Category = "Burrforce")
	FBurrforceConnectedEvent OnConnected;

	UFUNCTION(BlueprintCallable, Category = "Burrforce")
	void SetTool(USceneComponent* InTool) { Tool = InTool; }

	/// Asks the server for a new stream (its first tick has no velocity estimate). Never
	/// needed to recover: after a server restart or a REST restart-stream the server refuses
	/// the old stream and the component asks for a new one by itself.
	UFUNCTION(BlueprintCallable, Category = "Burrforce")
	void RestartStream();

	UFUNCTION(BlueprintCallable, Category = "Burrforce")
	bool IsStreaming() const;

	/// The streamer's newest bone version (game thread).
	uint64 GetLatestBoneVersion() const;
	/// The same for worker threads: holds the runtime, never this UObject.
	TFunction<uint64()> MakeBoneVersionSource() const;
	/// REST URL and token of the session (for UBurrforceBoneMeshComponent).
	bool GetRestAccess(FString& OutUrl, FString& OutToken, int32& OutSession) const;

	virtual void TickComponent(float DeltaTime, ELevelTick TickType,
		FActorComponentTickFunction* ThisTickFunction) override;

protected:
	virtual void BeginPlay() override;
	virtual void EndPlay(const EEndPlayReason::Type EndPlayReason) override;

private:
	void StartStreaming();
	void PublishPose();
	void ReadState();

	TSharedPtr<FBurrforceRuntime, ESPMode::ThreadSafe> Runtime;
	int32 LastStatus = -1;
	bool bReportedFailure = false;
};
